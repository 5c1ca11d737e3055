"""TIFF exports: float32 heights, and BigTIFF where a classic TIFF cannot hold them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import read_image, tiff
from merge.io.formats.exports import export_heights


def test_a_tiff_past_four_gigabytes_is_a_bigtiff(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import tifffile

    heights = np.random.default_rng(4).normal(0.0, 1e-9, (20, 30))
    small = export_heights(tmp_path / "small.tif", heights, pixel_size=(8e-9, 8e-9))
    monkeypatch.setattr(tiff, "BIGTIFF_FROM", heights.astype(np.float32).nbytes)
    big = export_heights(tmp_path / "big.tif", heights, pixel_size=(8e-9, 8e-9))
    with tifffile.TiffFile(small) as t, tifffile.TiffFile(big) as b:
        assert not t.is_bigtiff and b.is_bigtiff
    np.testing.assert_allclose(read_image(big).heights, heights, rtol=1e-6)


def test_a_memory_mapped_mosaic_is_written_strip_by_strip(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # strips of 7 rows (the last one short), top row first, from heights never copied whole
    import tifffile

    monkeypatch.setattr(tiff, "STRIP_BYTES", 4 * 30 * 7)
    stored = np.lib.format.open_memmap(tmp_path / "mosaic.npy", mode="w+", shape=(45, 30))
    stored[:] = np.random.default_rng(5).normal(0.0, 1e-9, (45, 30))
    stored[40:, :3] = np.nan
    stored.flush()
    heights = np.load(tmp_path / "mosaic.npy", mmap_mode="r")
    out = export_heights(tmp_path / "m.tif", heights, pixel_size=(8e-9, 8e-9))
    with tifffile.TiffFile(out) as t:
        assert len(t.pages.first.dataoffsets) == 7
    back = read_image(out).heights
    np.testing.assert_array_equal(np.isnan(back), np.isnan(heights))
    np.testing.assert_allclose(back, heights, rtol=1e-6)
