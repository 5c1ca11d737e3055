"""TIFF exports: float32 heights, and BigTIFF where a classic TIFF cannot hold them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from backend.formats import read_image, tiff
from backend.formats.exports import export_heights


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
