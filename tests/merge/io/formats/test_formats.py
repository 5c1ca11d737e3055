"""AFM readers and exports: real Nanosurf files, Gwyddion as the oracle of orientation,
every export opened by the tool it is meant for, and a whole round trip through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from backend.cli import main
from backend.synthetic import registration_error
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import ImageSurface
from hardware.sim.synth import synthesize
from merge import read_result
from merge.io.formats import FormatError, export_heights, read_image
from tests.conftest import SHARED_DATA
from tests.merge.io.formats.oracle import gwyddion_convert, needs_gwyddion

DATA = SHARED_DATA
pytestmark = pytest.mark.skipif(
    not (DATA / "mos2.nid").is_file(), reason=f"the real scans are not at {DATA}"
)


@pytest.mark.parametrize("name", ["mos2", "grid"])
def test_nid_equals_the_shipped_arrays(name: str) -> None:
    image = read_image(DATA / f"{name}.nid")
    reference = np.load(DATA / f"{name}.npy")
    assert image.channel == "Z-Axis forward" and image.unit == "m"
    np.testing.assert_array_equal(image.heights, reference)
    ny, nx = reference.shape
    assert image.pixel_size == pytest.approx(
        (3.97339e-6 / nx, 3.97339e-6 / ny) if name == "mos2" else (3e-6 / nx, 3e-6 / ny), rel=1e-4
    )
    assert "Phase forward" in image.channels or name == "grid"


def test_channels_are_selectable_and_missing_ones_named() -> None:
    amplitude = read_image(DATA / "mos2.nid", channel="Amplitude forward")
    assert amplitude.unit == "V" and amplitude.heights.shape == (256, 512)
    with pytest.raises(FormatError, match=r"no channel 'Bogus'.*Z-Axis forward"):
        read_image(DATA / "mos2.nid", channel="Bogus")


def test_wrong_or_cut_files_are_clear_errors(tmp_path: Path) -> None:
    cut = tmp_path / "cut.nid"
    cut.write_bytes((DATA / "mos2.nid").read_bytes()[:40000])
    with pytest.raises(FormatError, match="truncated"):
        read_image(cut)
    fake = tmp_path / "fake.gwy"
    fake.write_text("hello")
    with pytest.raises(FormatError, match="not a readable Gwyddion"):
        read_image(fake)
    with pytest.raises(FormatError, match="unknown AFM format"):
        read_image(tmp_path / "x.xyz")
    np.save(tmp_path / "h.npy", np.zeros((4, 4)))
    with pytest.raises(FormatError, match="pixel size"):
        read_image(tmp_path / "h.npy")


@needs_gwyddion
def test_nid_orientation_matches_gwyddion(tmp_path: Path) -> None:
    oracle = read_image(gwyddion_convert(DATA / "mos2.nid", tmp_path / "oracle.gwy"))
    ours = read_image(DATA / "mos2.nid")
    np.testing.assert_allclose(oracle.heights, ours.heights, rtol=0, atol=1e-15)
    assert oracle.pixel_size == pytest.approx(ours.pixel_size)


@needs_gwyddion
@pytest.mark.parametrize("suffix", [".gwy", ".tif"])
def test_our_files_open_in_gwyddion_the_right_way_up(tmp_path: Path, suffix: str) -> None:
    heights = np.load(DATA / "mos2.npy")[:40, :64]
    path = export_heights(tmp_path / f"m{suffix}", heights, pixel_size=(8e-9, 16e-9))
    back = gwyddion_convert(path, tmp_path / "back.gwy")
    channel = None if suffix == ".gwy" else "Gray"  # Gwyddion names a plain TIFF's channel
    seen = read_image(back, channel=channel)
    np.testing.assert_allclose(seen.heights, heights, rtol=1e-6, atol=1e-15)


def test_exports_open_in_their_tools(tmp_path: Path) -> None:
    import tifffile
    import trimesh

    heights = np.load(DATA / "mos2.npy")[:30, :40].copy()
    heights[0, 0] = np.nan
    size = (8e-9, 16e-9)
    tif = export_heights(tmp_path / "m.tif", heights, pixel_size=size)
    with tifffile.TiffFile(tif) as t:
        assert t.pages.first.dtype == np.float32
        xres = t.pages.first.tags["XResolution"].value
        assert 1e-2 * xres[1] / xres[0] == pytest.approx(8e-9)
    np.testing.assert_allclose(read_image(tif).heights, heights, rtol=1e-6)
    for suffix in (".ply", ".stl"):
        mesh = trimesh.load(export_heights(tmp_path / f"m{suffix}", heights, pixel_size=size))
        assert len(mesh.faces) == 2 * 29 * 39 - 2  # the NaN corner's cell is left out
        assert mesh.bounds[1][0] == pytest.approx(39 * 8e-9, rel=1e-5)
    png = export_heights(tmp_path / "m.png", heights, pixel_size=size).read_bytes()
    assert png.startswith(b"\x89PNG")
    npy = export_heights(tmp_path / "m.npy", heights, pixel_size=size)
    assert json.loads(npy.with_suffix(".json").read_text())["pixel_size"] == list(size)
    with pytest.raises(FormatError, match="unknown export format"):
        export_heights(tmp_path / "m.xyz", heights, pixel_size=size)


def test_round_trip_gwy_patches_import_merge_export(tmp_path: Path) -> None:
    """mos2 cut into drifting patches written as .gwy with their scan offsets, imported,
    merged, exported as .gwy and read back."""
    from merge.io.formats.gwy import write_gwy

    pitch = (3.97339e-6 / 512, 3.97339e-6 / 256)
    surface = ImageSurface(np.load(DATA / "mos2.npy"), pitch)
    synth = synthesize(
        surface,
        rows=2,
        cols=3,
        patch_size=(1.241e-6, 1.241e-6),
        pixels=(160, 80),
        overlap=(0.4, 0.4),
        drift=DriftModel.typical(),
        start=(0.25e-6, 0.25e-6),
        seed=2,
    )
    files = []
    for s in synth:
        path = tmp_path / "scans" / f"{s.id}.gwy"
        path.parent.mkdir(exist_ok=True)
        write_gwy(path, s.heights, pixel_size=s.pixel_size, origin=s.origin)
        files.append(str(path))
    assert main(["import", *files, "--out", str(tmp_path / "set")]) == 0
    manifest = json.loads((tmp_path / "set" / "manifest.json").read_text())
    origins = np.array([p["origin"] for p in manifest["patches"]])
    np.testing.assert_allclose(origins, [s.origin for s in synth], rtol=1e-12)
    out = tmp_path / "merged"
    assert (
        main(["merge", str(tmp_path / "set" / "manifest.json"), "--out", str(out), "--quiet"]) == 0
    )
    result = read_result(out)
    exy, ez, _ = registration_error(synth, list(result.transforms.values()))
    assert exy < 2e-9 and ez < 1.5e-9  # the merge issue's targets
    assert main(["export", str(out), "--format", "gwy"]) == 0
    back = read_image(out / "mosaic.gwy")
    m = result.mosaic
    np.testing.assert_allclose(
        back.heights, np.where(np.isfinite(m.heights), m.heights, back.heights)
    )
    assert back.pixel_size == pytest.approx(m.pixel_size) and back.unit == "m"
    assert back.offset == pytest.approx(m.origin)


def test_convert_and_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["convert", str(DATA / "grid.nid"), str(tmp_path / "grid.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "grid.npy"), np.load(DATA / "grid.npy"))
    side = json.loads((tmp_path / "grid.json").read_text())
    assert side["channel"] == "Z-Axis forward" and side["pixel_size"][0] == pytest.approx(
        3e-6 / 256
    )
    assert main(["convert", str(tmp_path / "missing.nid"), str(tmp_path / "x.gwy")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["import", str(tmp_path / "grid.npy"), "--out", str(tmp_path / "s")]) == 2
    assert "needs two at least" in capsys.readouterr().err
    (tmp_path / "grid2.npy").write_bytes((tmp_path / "grid.npy").read_bytes())
    pair = [str(tmp_path / "grid.npy"), str(tmp_path / "grid2.npy"), "--pixel-size", "1e-8"]
    assert main(["import", *pair, "--out", str(tmp_path / "s")]) == 2
    said = capsys.readouterr().err
    assert "grid.npy, grid2.npy carry no scan offset" in said and "--grid" in said
