"""Tilts of patches levelled one by one: recognised, measured from overlaps, taken off."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy import ndimage

from merge.core.downsample import GridSample
from merge.start.tilts import (
    levelled_one_by_one,
    own_plane_change,
    patch_tilts,
    slope_difference,
    untilted,
)

FloatArray = NDArray[np.float64]
CELL = 20e-9


def _ground(seed: int = 0, shape: tuple[int, int] = (120, 160)) -> FloatArray:
    """A stepped, textured lattice (metres): terraces 300 nm apart and a fine roughness."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]]
    steps = 300e-9 * (((xx // 50) + (yy // 40)) % 2)
    steps = ndimage.gaussian_filter(steps.astype(np.float64), 3.0)
    out: FloatArray = steps + ndimage.gaussian_filter(rng.normal(0, 6e-9, shape), 1.5)
    return out


def _levelled(h: FloatArray) -> FloatArray:
    ny, nx = h.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    A = np.column_stack([np.ones(h.size), xx.ravel(), yy.ravel()])
    out: FloatArray = h - (A @ np.linalg.lstsq(A, h.ravel(), rcond=None)[0]).reshape(ny, nx)
    return out


def _grid(h: FloatArray, row: int, col: int) -> GridSample:
    ny, nx = h.shape
    return GridSample(
        heights=h,
        counts=np.ones(h.shape, dtype=np.int64),
        x=(col + np.arange(nx, dtype=np.float64)) * CELL,
        y=(row + np.arange(ny, dtype=np.float64)) * CELL,
        cell=CELL,
    )


def test_a_patch_levelled_by_its_own_plane_is_recognised() -> None:
    h = _ground()[:40, :60]
    assert own_plane_change(h) > 1e-3  # raw: its own plane is not flat
    assert own_plane_change(_levelled(h)) < 1e-10
    # stored as float32, levelled patches still read as levelled
    assert own_plane_change(_levelled(h).astype(np.float32).astype(np.float64)) < 1e-5
    assert np.isnan(own_plane_change(np.full((5, 5), 3.0)))  # nothing to tell from
    patches = [_ground(s)[:40, :60] for s in range(5)]
    assert not levelled_one_by_one(patches)
    assert levelled_one_by_one([_levelled(h) for h in patches])
    assert not levelled_one_by_one([_levelled(h) for h in patches[:3]] + patches[3:])


def test_slope_difference_measures_a_tilt_whatever_the_offset() -> None:
    ground = _ground()
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float64)
    a = ground[10:70, 20:100]
    b = ground[10:70, 50:130] + 0.02 * CELL * xx - 0.01 * CELL * yy + 1e-6
    slopes = []
    for h in (a, b):
        gy, gx = np.gradient(h)
        slopes.append(np.stack([gx, gy]))
    med, var, count = slope_difference(slopes[0], slopes[1], (0, -30))
    np.testing.assert_allclose(med / CELL, [0.02, -0.01], atol=1e-9)
    assert count == 60 * 50 and var < 1e-30 * 10  # the same ground: no spread at all
    assert slope_difference(slopes[0], slopes[1], (0, -79))[2] == 0  # too small to measure


@pytest.mark.parametrize("misplaced", [0, 3])
def test_patch_tilts_are_recovered_from_the_overlaps(misplaced: int) -> None:
    # four patches on a 2 x 2 grid, each levelled by its own plane and then tilted by a known
    # amount; the stage put each a few cells off its nominal place
    ground = _ground(seed=4)
    rng = np.random.default_rng(1)
    nominal = [(10, 10), (10, 60), (50, 10), (50, 60)]
    true_tilt = rng.normal(0.0, 0.05, (4, 2))
    yy, xx = np.mgrid[0:60, 0:90] * CELL
    A = np.column_stack([np.ones(xx.size), xx.ravel(), yy.ravel()])
    grids, offsets, taken_off = [], [], []
    for (r, c), tilt in zip(nominal, true_tilt, strict=True):
        dr, dc = rng.integers(-misplaced, misplaced + 1, 2)
        window = ground[r + dr : r + dr + 60, c + dc : c + dc + 90]
        taken_off.append(np.linalg.lstsq(A, window.ravel(), rcond=None)[0][1:])
        grids.append(_grid(_levelled(window) + tilt[0] * xx + tilt[1] * yy, r, c))
        offsets.append((r, c))
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    found = patch_tilts(
        grids, offsets, pairs, np.ones(len(pairs), dtype=bool), radius=6.0, min_overlap=[16] * 6
    )
    # what each patch holds against the ground: the tilt added, less the plane its levelling
    # took off; the mean is what no overlap can tell (the sample's own tilt)
    expected = true_tilt - np.array(taken_off)
    expected -= expected.mean(axis=0)
    expected -= expected.mean(axis=0)
    np.testing.assert_allclose(found - found.mean(axis=0), expected, atol=0.004)
    assert np.abs(expected).max() > 0.03  # tilts that matter: 60 nm ramps over a patch


def test_untilted_takes_off_a_plane_zero_at_the_centre() -> None:
    g = _grid(np.zeros((10, 20)), 0, 0)
    out = untilted(g, np.array([0.1, -0.2]), (10 * CELL, 5 * CELL))
    assert out.heights[5, 10] == pytest.approx(0.0)
    assert out.heights[5, 11] - out.heights[5, 10] == pytest.approx(-0.1 * CELL)
    assert out.heights[6, 10] - out.heights[5, 10] == pytest.approx(0.2 * CELL)
