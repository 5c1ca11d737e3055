"""The streaming .gwy writer: Gwyddion's serialisation, written a block of rows at a time."""

from __future__ import annotations

from pathlib import Path

import gwyfile
import numpy as np
import pytest
from gwyfile.objects import GwyContainer, GwyDataField, GwySIUnit

from merge.io.formats import gwy
from merge.io.formats.image import FormatError


def _gwyfile_bytes(path: Path, h: np.ndarray, pixel: tuple[float, float]) -> bytes:
    """What gwyfile (which builds the file in memory) writes for the same field, mask and
    metadata."""
    ny, nx = h.shape

    def field(values: np.ndarray, unit: str) -> GwyDataField:
        return GwyDataField(
            np.ascontiguousarray(values[::-1]),
            xreal=nx * pixel[0],
            yreal=ny * pixel[1],
            xoff=1e-6 - pixel[0] / 2,
            # the top-left corner, y down: our origin (-2 µm) is the bottom-left pixel's centre
            yoff=-(-2e-6 - pixel[1] / 2 + ny * pixel[1]),
            si_unit_xy=GwySIUnit(unitstr="m"),
            si_unit_z=GwySIUnit(unitstr=unit),
        )

    c = GwyContainer()
    c["/0/data"] = field(np.nan_to_num(h, nan=float(np.nanmin(h))), "m")
    c["/0/data/title"] = "Height"
    c["/0/mask"] = field((~np.isfinite(h)).astype(np.float64), "")
    meta = GwyContainer()
    meta["Software"] = "mosaic-afm"
    meta["iterations"] = "12"
    c["/0/meta"] = meta
    c.tofile(str(path))
    return path.read_bytes()


def test_blocks_of_rows_write_what_gwyfile_writes_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rng = np.random.default_rng(0)
    h = rng.normal(size=(37, 53)) * 1e-9
    h[3, 4] = h[30, 50] = np.nan
    monkeypatch.setattr(gwy, "BLOCK_BYTES", 8 * 53 * 5)  # eight blocks, the last short
    gwy.write_gwy(
        tmp_path / "ours.gwy",
        h,
        pixel_size=(2e-9, 3e-9),
        origin=(1e-6, -2e-6),
        metadata={"Software": "mosaic-afm", "iterations": "12"},
    )
    expected = _gwyfile_bytes(tmp_path / "theirs.gwy", h, (2e-9, 3e-9))
    assert (tmp_path / "ours.gwy").read_bytes() == expected


def test_a_memory_mapped_mosaic_is_written_and_read_back(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    stored = np.lib.format.open_memmap(tmp_path / "mosaic.npy", mode="w+", shape=(300, 200))
    stored[:] = rng.normal(size=(300, 200)) * 1e-9
    stored[:10, :] = np.nan
    stored.flush()
    heights = np.load(tmp_path / "mosaic.npy", mmap_mode="r")
    gwy.write_gwy(tmp_path / "m.gwy", heights, pixel_size=(1e-9, 1e-9))
    back = gwy.read_gwy(tmp_path / "m.gwy")
    finite = np.isfinite(heights)
    np.testing.assert_array_equal(back.heights[finite], heights[finite])
    # the holes hold the lowest height (Gwyddion's fields have no NaN); the mask marks them
    assert (back.heights[~finite] == np.nanmin(heights)).all()
    mask = gwyfile.load(str(tmp_path / "m.gwy"))["/0/mask"].data[::-1]
    np.testing.assert_array_equal(mask, (~finite).astype(np.float64))


def test_a_field_past_what_the_format_holds_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(gwy, "MAX_OBJECT", 10_000)
    with pytest.raises(FormatError, match=r"more than a \.gwy file can hold.*\.tif"):
        gwy.write_gwy(tmp_path / "big.gwy", np.zeros((40, 40)), pixel_size=(1e-9, 1e-9))
    assert not (tmp_path / "big.gwy").exists()
