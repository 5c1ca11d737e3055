"""Scoring a mosaic against a reference recovers known shifts, offsets and local errors."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.sim.surfaces import FoldedSurface
from merge.report.evaluate import Grid, score_mosaic


def _grid(surface: FoldedSurface, x0: float, y0: float, n: int, pitch: float) -> np.ndarray:
    xx, yy = np.meshgrid(x0 + pitch * np.arange(n), y0 + pitch * np.arange(n))
    return np.asarray(surface.height(xx, yy))


@pytest.fixture(scope="module")
def reference() -> tuple[FoldedSurface, Grid]:
    surface = FoldedSurface(seed=3)
    return surface, Grid(
        _grid(surface, -0.3e-6, -0.3e-6, 260, 10e-9), (-0.3e-6, -0.3e-6), (10e-9,) * 2
    )


def test_a_shifted_levelled_copy_scores_as_perfect(reference: tuple[FoldedSurface, Grid]) -> None:
    surface, ref = reference
    shift = (37e-9, -21e-9)
    heights = _grid(surface, shift[0], shift[1], 100, 20e-9)
    xx = np.arange(100)[None, :]
    heights = heights + 5e-9 + 1e-4 * xx * 20e-9  # offset and tilt are not errors
    score = score_mosaic(Grid(heights, (0.0, 0.0), (20e-9,) * 2), ref, tile=(0.5e-6, 0.5e-6))
    assert score.shift == pytest.approx(shift, abs=0.2e-9)
    assert score.map_rms < 0.1e-9 and score.tile_xy_rms < 0.2e-9 and score.tile_z_rms < 0.1e-9


def test_a_misplaced_quarter_shows_in_the_tiles(reference: tuple[FoldedSurface, Grid]) -> None:
    surface, ref = reference
    heights = _grid(surface, 0.0, 0.0, 100, 20e-9)
    heights[:50, :50] = _grid(surface, 8e-9, 0.0, 50, 20e-9)  # one quarter 8 nm off in x
    score = score_mosaic(Grid(heights, (0.0, 0.0), (20e-9,) * 2), ref, tile=(1e-6, 1e-6))
    dx = score.tile_shifts[:, 0]
    assert dx.max() - dx.min() == pytest.approx(8e-9, abs=0.5e-9)
    assert score.tile_xy_rms == pytest.approx(np.sqrt(3) / 4 * 8e-9, rel=0.15)


def test_bad_input_is_a_value_error(reference: tuple[FoldedSurface, Grid]) -> None:
    _, ref = reference
    with pytest.raises(ValueError, match="2-D"):
        Grid(np.zeros(5), (0, 0), (1e-9, 1e-9))
    with pytest.raises(ValueError, match="tile"):
        score_mosaic(ref, ref, tile=(0, 1e-6))
    with pytest.raises(ValueError, match="finite"):
        score_mosaic(Grid(np.full((5, 5), np.nan), (0, 0), (1e-8,) * 2), ref, tile=(1e-7, 1e-7))
