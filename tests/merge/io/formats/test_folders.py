"""A folder of overlapping scans as AFM users have them: a real image cut into tiles, each
written in its format's own convention (where its offsets point, which row comes first), with
stage errors, Z offsets, tilts and noise; imported and merged, the tiles must lie where they
were cut and the mosaic must match the image within the noise."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import merge
from backend.cli import main
from backend.synthetic import scored
from hardware.sim.synth import SynthPatch
from merge.io.formats.gwy import _fields
from tests.conftest import SHARED_DATA
from tests.merge.io.formats.test_ibw import write_ibw
from tests.merge.io.formats.test_nanoscope import write_nanoscope
from tests.merge.io.formats.test_park import V2, park_header, write_park
from tests.merge.io.formats.test_sxm import write_sxm

IMAGE = SHARED_DATA / "mos2.npy"
PIXEL = (3.97339e-6 / 512, 3.97339e-6 / 256)  # mos2: 7.76 x 15.52 nm, not square
needs_image = pytest.mark.skipif(not IMAGE.is_file(), reason=f"no real scan at {IMAGE}")

#: A 3 x 3 grid of tiles of 200 x 100 px (1.55 µm square), a third overlapping.
TILE = (100, 200)  # rows, cols
STEP = (66, 133)


def _tiles(seed: int = 5) -> list[tuple[SynthPatch, np.ndarray]]:
    """The tiles, each as the truth (where it was cut, how it was spoiled) and the heights an
    instrument recorded (rows along +y, metres)."""
    image = np.load(IMAGE)
    rng = np.random.default_rng(seed)
    out = []
    for r in range(3):
        for c in range(3):
            i0, j0 = r * STEP[0], c * STEP[1]
            true = image[i0 : i0 + TILE[0], j0 : j0 + TILE[1]]
            cut = (j0 * PIXEL[0], i0 * PIXEL[1])  # the pixel (0, 0) of the tile
            stage_error = rng.uniform(-40e-9, 40e-9, 2)
            z0, a, b = rng.normal(0, 5e-9), rng.normal(0, 2e-3), rng.normal(0, 2e-3)
            yy, xx = np.mgrid[0 : TILE[0], 0 : TILE[1]]
            x, y = xx * PIXEL[0], yy * PIXEL[1]
            recorded = true + z0 + a * x + b * y + rng.normal(0, 0.2e-9, true.shape)
            nominal = (cut[0] + stage_error[0], cut[1] + stage_error[1])
            # the truth maps a recorded point (nominal place, recorded height) to where it is
            rotation = Rotation.from_rotvec([-b, a, 0.0]).as_matrix()
            p0 = np.array([nominal[0], nominal[1], recorded[0, 0]])
            q0 = np.array([cut[0], cut[1], true[0, 0]])
            truth = SynthPatch(
                id=f"r{r}c{c}",
                heights=recorded,
                origin=nominal,
                pixel_size=PIXEL,
                order=3 * r + c,
                row=r,
                col=c,
                rotation=rotation,
                translation=q0 - rotation @ p0,
                z_drift=0.0,
            )
            out.append((truth, recorded))
    return out


def write_gwy_tile(path: Path, patch: SynthPatch) -> None:
    """As Gwyddion writes it (with ``gwyfile``): row 0 at the top, ``xoff``/``yoff`` the
    top-left corner, y growing down the rows."""
    from gwyfile.objects import GwyContainer, GwyDataField

    ny, nx = patch.heights.shape
    dx, dy = patch.pixel_size
    top = patch.origin[1] + (ny - 0.5) * dy  # our top edge, y up
    field = GwyDataField(
        patch.heights[::-1].copy(),
        xreal=nx * dx,
        yreal=ny * dy,
        xoff=patch.origin[0] - dx / 2,
        yoff=-top,
        si_unit_xy="m",
        si_unit_z="m",
    )
    container = GwyContainer()
    container["/0/data"] = field
    container["/0/data/title"] = "Height"
    container.tofile(str(path))


def _centre(patch: SynthPatch) -> tuple[float, float]:
    """The scan's centre, which NanoScope, Nanonis and Park headers give as its offset."""
    ny, nx = patch.heights.shape
    (dx, dy), (x0, y0) = patch.pixel_size, patch.origin
    return float(x0 + (nx - 1) * dx / 2), float(y0 + (ny - 1) * dy / 2)


def _size(patch: SynthPatch) -> tuple[float, float]:
    ny, nx = patch.heights.shape
    return float(nx * patch.pixel_size[0]), float(ny * patch.pixel_size[1])


def write_nanoscope_tile(path: Path, patch: SynthPatch) -> None:
    """Bruker NanoScope: 32-bit counts, the bottom line first, X/Y offset the scan's centre
    (in nm), the scan size in µm."""
    hard, lsb = 10.0, 10.0 * 20e-9 / 2.0**32  # V, metres per count at 20 nm/V
    raw = np.round(patch.heights / lsb).astype(np.int64)
    (w, h), (cx, cy) = _size(patch), _centre(patch)
    write_nanoscope(
        path,
        [("Height", raw, 4, hard, "Sens. Zsens", "Retrace")],
        scan_size=f"{w * 1e6!r} {h * 1e6!r} ~m",
        offset=(f"{cx * 1e9!r} nm", f"{cy * 1e9!r} nm"),
    )


def write_sxm_tile(path: Path, patch: SynthPatch) -> None:
    """Nanonis .sxm: float32 frames, scanned up (the bottom line first), SCAN_OFFSET the
    scan's centre in the scan frame (y up)."""
    frames = [("Z", "m", patch.heights, None)]
    write_sxm(path, frames, scan_range=_size(patch), centre=_centre(patch), up=True)


def write_park_tile(path: Path, patch: SynthPatch) -> None:
    """Park Systems TIFF (version 2, float32 in µm): the bottom line first, the header's
    offset the scan's centre in µm."""
    (w, h), (cx, cy) = _size(patch), _centre(patch)
    head = park_header(
        patch.heights.shape,
        size_um=(w * 1e6, h * 1e6),
        centre_um=(cx * 1e6, cy * 1e6),
        gain=1.0,
        unit="um",
        data_type=2,
    )
    write_park(path, (patch.heights * 1e6).astype("<f4"), head, V2)


def write_ibw_tile(path: Path, patch: SynthPatch) -> None:
    """Asylum .ibw: the wave's x/y scaling starts at pixel (0, 0), y up."""
    layers = patch.heights[None].astype(np.float32)
    write_ibw(path, layers, ["HeightRetrace"], pixel=patch.pixel_size, first=patch.origin)


def write_nid_tile(path: Path, patch: SynthPatch) -> None:
    """Nanosurf .nid: 32-bit counts over the Z range, the first line stored first (the
    bottom), ``ScanOffset`` the scan's centre and the channel's own Dim0Min/Dim1Min 0."""
    ny, nx = patch.heights.shape
    (w, h), (cx, cy) = _size(patch), _centre(patch)
    zmin, zrange = float(patch.heights.min()) - 1e-9, float(np.ptp(patch.heights)) + 2e-9
    raw = np.round((patch.heights - zmin) / zrange * 2.0**32 - 2.0**31)
    raw = np.clip(raw, -(2**31), 2**31 - 1).astype("<i4")
    header = "\r\n".join([
        "[DataSet]", "Version=2", "GroupCount=1", "Gr0-Name=Scan forward", "Gr0-ID=0",
        "Gr0-Count=1", "Gr0-Ch0=DataSet-0:1", "",
        "[DataSet-Info]", "Rotation=0 \u00b0", "",
        "[DataSet\\Parameters\\Imaging]", f"ScanOffset=V[{cx!r},{cy!r},0]*[m,m,m]", "",
        "[DataSet-0:1]", f"Points={nx}", f"Lines={ny}", "SaveBits=32", "SaveSign=Signed",
        f"Dim0Range={w!r}", "Dim0Min=0", f"Dim1Range={h!r}", "Dim1Min=0", "Dim2Name=Z-Axis",
        "Dim2Unit=m", f"Dim2Range={zrange!r}", f"Dim2Min={zmin!r}", "",
    ])  # fmt: skip
    path.write_bytes(header.encode("latin-1") + b"#!" + raw.tobytes())


WRITERS: dict[str, Callable[[Path, SynthPatch], None]] = {
    ".nid": write_nid_tile,
    ".gwy": write_gwy_tile,
    ".spm": write_nanoscope_tile,
    ".sxm": write_sxm_tile,
    ".tiff": write_park_tile,
    ".ibw": write_ibw_tile,
}


@needs_image
@pytest.mark.parametrize("suffix", sorted(WRITERS))
def test_a_folder_of_tiles_lies_where_they_were_cut_and_merges_to_the_image(
    tmp_path: Path, suffix: str
) -> None:
    tiles = _tiles()
    folder = tmp_path / "scans"
    folder.mkdir()
    for truth, _ in tiles:
        WRITERS[suffix](folder / f"{truth.id}{suffix}", truth)
    files = sorted(str(p) for p in folder.iterdir())
    assert main(["import", *files, "--out", str(tmp_path / "set")]) == 0
    manifest = merge.read_patch_set(tmp_path / "set" / "manifest.json")
    by_id = {t.id: t for t, _ in tiles}
    for patch, path in zip(manifest.patches, files, strict=True):
        truth = by_id[Path(path).stem]
        assert patch.origin == pytest.approx(truth.origin, abs=1e-12)  # where the file says
    out = tmp_path / "merged"
    assert main(["merge", str(tmp_path / "set" / "manifest.json"), "--out", str(out)]) == 0
    result = merge.read_result(out)
    transforms = result.transforms
    order = [Path(f).stem for f in files]
    s = scored([by_id[k] for k in order], [transforms[p.id] for p in manifest.patches])
    assert s.xy < 2e-9 and s.z < 0.4e-9, (s.xy, s.z)


def _folder(tmp_path: Path) -> Path:
    folder = tmp_path / "scans"
    folder.mkdir()
    for truth, _ in _tiles():
        write_gwy_tile(folder / f"{truth.id}.gwy", truth)
    return folder


@needs_image
def test_a_folder_merges_in_one_step_with_a_plain_verdict(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _folder(tmp_path)
    assert main(["merge", str(folder), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("CONFIRMED: every patch's place measured") and "9 patches" in last
    # the Python API reads what the CLI reads
    patch_set = merge.read_scans(folder)
    assert [p.id for p in patch_set] == [f"r{r}c{c}" for r in range(3) for c in range(3)]


@needs_image
def test_tiles_that_overlap_nothing_are_written_but_not_trusted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "apart"
    folder.mkdir()
    for truth, _ in _tiles()[:3]:  # one row of tiles, then spread 10 µm apart
        far = dataclasses.replace(truth, origin=(truth.origin[0] * 10, truth.origin[1]))
        write_gwy_tile(folder / f"{truth.id}.gwy", far)
    assert main(["merge", str(folder), "--out", str(tmp_path / "m"), "--quiet"]) == 3
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("NOT TRUSTED") and "overlap" in last
    assert (tmp_path / "m" / "mosaic.npy").is_file()  # written all the same


@needs_image
def test_an_unreadable_file_stops_the_folder_by_name_unless_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = _folder(tmp_path)
    (folder / "r9c9.gwy").write_bytes(b"GWYPnot really")
    assert main(["import", str(folder), "--out", str(tmp_path / "s")]) == 2
    assert "r9c9.gwy" in capsys.readouterr().err
    assert main(["import", str(folder), "--out", str(tmp_path / "s"), "--skip-bad"]) == 0
    said = capsys.readouterr()
    assert "skipped" in said.err and "r9c9.gwy" in said.err and "9 patches" in said.out


@needs_image
def test_the_exported_gwy_lies_where_the_input_files_lie_in_gwyddion(tmp_path: Path) -> None:
    folder = _folder(tmp_path)
    assert main(["merge", str(folder), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    assert main(["export", str(tmp_path / "m"), "--format", "gwy"]) == 0

    def corner(path: Path) -> tuple[float, float, float, float]:
        """The field's top-left corner as Gwyddion has it, and its far corner."""
        field = _fields(path)[0][1]
        x, y = float(field.get("xoff", 0.0)), float(field.get("yoff", 0.0))
        return x, y, x + float(field["xreal"]), y + float(field["yreal"])

    tiles = [corner(p) for p in sorted(folder.glob("*.gwy"))]
    mosaic = corner(tmp_path / "m" / "mosaic.gwy")
    union = (
        min(t[0] for t in tiles),
        min(t[1] for t in tiles),
        max(t[2] for t in tiles),
        max(t[3] for t in tiles),
    )
    # within the stage errors the merge corrects (±40 nm) and a pixel of the mosaic
    assert mosaic == pytest.approx(union, abs=60e-9)


@needs_image
def test_the_python_example_merges_a_folder_as_printed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from examples import merge_folder

    assert merge_folder.main([str(_folder(tmp_path)), str(tmp_path / "m")]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("CONFIRMED")


@needs_image
def test_a_real_nid_lies_at_its_scan_offset_and_a_rotated_one_is_not_placed_by_it(
    tmp_path: Path,
) -> None:
    from merge.io.formats import read_image

    mos2 = read_image(SHARED_DATA / "mos2.nid")  # ScanOffset=V[-1.84326e-06,-4.27246e-07,...]
    dx, dy = mos2.pixel_size
    assert mos2.offset == pytest.approx(
        (-1.84326e-06 - 3.97339e-6 / 2 + dx / 2, -4.27246e-07 - 3.97339e-6 / 2 + dy / 2)
    )
    grid = read_image(SHARED_DATA / "grid.nid")  # scanned at 45°
    assert grid.metadata["rotation_deg"] == "45"
    with pytest.raises(merge.PatchSetError, match=r"grid.nid \(45°\) were scanned rotated"):
        merge.read_scans([SHARED_DATA / "mos2.nid", SHARED_DATA / "grid.nid"])
