"""The sources' smoothed slopes: their kernel, their noise, and where rows take them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from merge.core.heightfield import slope_noise
from merge.refine.runs import RowBlock
from merge.refine.source_slopes import (
    AGREE,
    FLAT,
    TRUNCATE,
    SourceSlopes,
    gaussian_slope_noise,
    gaussian_slopes,
    slopes_in_destination,
)


@pytest.mark.parametrize("width", [1.0, 1.5, 3.0])
def test_gaussian_slopes_are_exact_on_a_plane_and_undefined_near_border_and_holes(
    width: float,
) -> None:
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    heights = 0.3 * xx * 2.0 - 0.2 * yy * 0.5  # pitch 2 along x, 0.5 along y
    heights[20, 25] = np.nan
    g = gaussian_slopes(heights, width, (2.0, 0.5))
    reach = int(TRUNCATE * width + 0.5)
    edge = reach // 2 + 1
    defined = np.isfinite(g).all(axis=2)
    assert not defined[:edge].any() and not defined[:, -edge:].any()
    assert not defined[20 - reach : 21 + reach, 25 - reach : 26 + reach].any()
    assert defined[edge:-edge, edge : 25 - reach].all()
    # exact where the kernel sees only the plane; nearer the border the mirror bends it
    inner = np.zeros_like(defined)
    inner[reach:-reach, reach:-reach] = True
    inner &= defined
    np.testing.assert_allclose(g[inner], np.broadcast_to([0.3, -0.2], g[inner].shape), atol=1e-9)


def test_gaussian_slopes_share_no_noise_with_their_own_pixel() -> None:
    # the pixel's own height has no weight in its slope, at the border band too
    rng = np.random.default_rng(2)
    base = rng.normal(size=(30, 30))
    g0 = gaussian_slopes(base, 1.5, (1.0, 1.0))
    for i, j in [(5, 5), (4, 15), (15, 25), (12, 12)]:
        bumped = base.copy()
        bumped[i, j] += 1.0
        g1 = gaussian_slopes(bumped, 1.5, (1.0, 1.0))
        assert np.isnan(g1[i, j]).all() or np.allclose(g1[i, j], g0[i, j], atol=1e-12)
        assert np.isfinite(g1[i, j]).all() == (i >= 4 and j >= 4 and i < 26 and j < 26)


def test_gaussian_slopes_refuse_what_they_cannot_smooth() -> None:
    with pytest.raises(ValueError, match="width"):
        gaussian_slopes(np.zeros((8, 8)), 0.0, (1.0, 1.0))
    with pytest.raises(ValueError, match="2-D"):
        gaussian_slopes(np.zeros(8), 1.0, (1.0, 1.0))


@pytest.mark.parametrize("width", [1.0, 2.0])
def test_the_smoothed_slopes_noise_is_what_its_kernel_says_and_below_a_look_ups(
    width: float,
) -> None:
    rng = np.random.default_rng(4)
    g = gaussian_slopes(rng.normal(size=(400, 400)), width, (1.0, 1.0))
    inner = g[10:-10, 10:-10]
    measured = inner.reshape(-1, 2).var(axis=0)
    np.testing.assert_allclose(measured, gaussian_slope_noise(width), rtol=0.05)
    assert gaussian_slope_noise(width) < 0.2 * slope_noise(2)


def test_on_a_smooth_noisy_surface_the_smoothed_slopes_are_nearer_the_truth() -> None:
    # a surface smooth at the pixel scale (correlation 8 px) under noise as strong as its
    # slopes: what a 1 µm grating's flat face is in 5 nm pixels
    rng = np.random.default_rng(7)
    truth = ndimage.gaussian_filter(rng.normal(size=(200, 200)), 8.0) * 40.0
    exact = np.stack(np.gradient(truth)[::-1], axis=2)
    noisy = truth + rng.normal(0.0, 0.3, truth.shape)
    central = np.stack(np.gradient(noisy)[::-1], axis=2)
    smoothed = gaussian_slopes(noisy, 1.5, (1.0, 1.0))
    inner = (slice(10, -10), slice(10, -10))
    err_central = np.mean((central[inner] - exact[inner]) ** 2)
    err_smoothed = np.mean((smoothed[inner] - exact[inner]) ** 2)
    assert err_smoothed < 0.25 * err_central


def _rows(src: list[int], row: list[int], col: list[int]) -> RowBlock:
    """One run per source patch given in order, all onto patch 9."""
    src_a = np.asarray(src, dtype=np.intp)
    cut = np.flatnonzero(np.diff(src_a)) + 1
    starts = np.concatenate([[0], cut, [len(src_a)]]).astype(np.intp)
    return RowBlock(
        src=src_a,
        dst=np.full(len(src_a), 9, dtype=np.intp),
        row=np.asarray(row, dtype=np.intp),
        col=np.asarray(col, dtype=np.intp),
        starts=starts,
        groups=starts[:-1].copy(),
    )


def test_rows_take_the_smoothed_slopes_only_where_flat_and_agreeing() -> None:
    grid = np.zeros((4, 4, 2), dtype=np.float16)
    grid[..., 0] = 0.1
    grid[3, 3] = (2.0 * FLAT, 0.0)  # a ramp: too steep to smooth
    spread2 = 0.01
    slopes = SourceSlopes({0: grid}, spread2, 0.1, 1.5)
    rows = _rows([0, 0, 0, 0, 1], [0, 1, 2, 3, 0], [0, 1, 2, 3, 0])
    far = 0.1 + 1.01 * AGREE * np.sqrt(spread2)  # more apart than the spread allows
    grad = np.array([[0.12, 0.0], [far, 0.0], [0.1, 0.0], [2.0 * FLAT, 0.0], [0.3, 0.3]])
    ok = np.array([True, True, False, True, True])
    before = grad.copy()
    own = slopes.take(rows, ok, grad, np.repeat(np.eye(3)[None], 2, axis=0))
    np.testing.assert_array_equal(own, [True, False, False, False, False])
    np.testing.assert_allclose(grad[0], [0.1, 0.0], atol=1e-3)  # float16 storage
    np.testing.assert_array_equal(grad[1:], before[1:])


def test_source_slopes_go_into_the_destination_frame_as_a_plane_through_mapped_points() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        angle = rng.normal(0.0, 0.05)
        M = np.eye(3)
        M[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        M[2, :2] = rng.normal(0.0, 0.01, 2)  # drift planes
        M[:2, 2] = rng.normal(0.0, 0.01, 2)  # a tilted frame
        g = rng.normal(0.0, 0.5, 2)
        # three points of the source's plane, mapped: the plane through them in the destination
        p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, g[0]], [0.0, 1.0, g[1]]]) @ M.T
        d = p[1:] - p[0]
        expected = np.linalg.solve(d[:, :2], d[:, 2])
        got = slopes_in_destination(g[None, :], M[None])[0]
        np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-12)
