"""Height maps as surfaces: NaN-aware smoothing, upsampling and bilinear look-ups."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from merge.core.heightfield import bilinear, slope_noise, smooth_nan, upsample2

FloatArray = NDArray[np.float64]


def _plane(shape: tuple[int, int] = (24, 32)) -> FloatArray:
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    out: FloatArray = 2.5 * xx - 1.5 * yy + 7.0
    return out


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_smoothing_leaves_a_plane_alone_up_to_its_border(sigma: float) -> None:
    # the flank of a step crossing a patch border: repeating the border value would bend it
    # there by about slope x sigma (2.5 px x 1 px here)
    h = _plane()
    np.testing.assert_allclose(smooth_nan(h, sigma, border="mirror"), h, atol=1e-9)
    # repeating the border value bends it there (the default, for narrow smoothing)
    assert np.abs(smooth_nan(h, sigma) - h)[:, 0].max() > 0.2 * 2.5 * sigma


def test_smoothing_keeps_holes_and_fills_nothing() -> None:
    h = _plane()
    h[10:13, 5:9] = np.nan
    h[0, 0] = np.nan
    out = smooth_nan(h, 1.0, border="mirror")
    np.testing.assert_array_equal(np.isnan(out), np.isnan(h))
    # away from the holes the plane is untouched
    np.testing.assert_allclose(out[18:, 15:], h[18:, 15:], atol=1e-9)


def test_smoothing_a_patch_smaller_than_the_filter_still_works() -> None:
    h = _plane((5, 6))
    out = smooth_nan(h, 2.0, border="mirror")
    assert out.shape == h.shape and np.isfinite(out).all()
    # the mean level survives even where the border cannot be continued
    assert abs(out.mean() - h.mean()) < 1.0


def test_smoothing_removes_noise() -> None:
    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 1.0, (64, 64))
    assert np.std(smooth_nan(noise, 2.0)) < 0.2


def test_bilinear_is_exact_on_a_plane() -> None:
    h = _plane()
    (val,), ok = bilinear([h], np.array([0.0, 3.25, 23.0, 23.5]), np.array([0.0, 7.5, 31.0, 2.0]))
    np.testing.assert_array_equal(ok, [True, True, True, False])
    expected = [7.0, 2.5 * 7.5 - 1.5 * 3.25 + 7.0, 2.5 * 31.0 - 1.5 * 23.0 + 7.0]
    np.testing.assert_allclose(val[:3], expected)


def test_upsampling_keeps_the_pixels_and_a_plane_everywhere() -> None:
    h = _plane((9, 12))
    fine = upsample2(h)
    assert fine.shape == (17, 23)
    np.testing.assert_allclose(fine[::2, ::2], h, atol=1e-12)
    yy, xx = np.mgrid[0:17, 0:23] / 2.0
    np.testing.assert_allclose(fine, 2.5 * xx - 1.5 * yy + 7.0, atol=1e-9)


def test_upsampling_with_a_margin_continues_beyond_the_border() -> None:
    h = _plane((9, 12))
    fine = upsample2(h, margin=1)
    assert fine.shape == (21, 27)
    np.testing.assert_allclose(fine[2:-2, 2:-2], upsample2(h), atol=1e-12)
    yy, xx = np.mgrid[0:21, 0:27] / 2.0 - 1.0  # pixels -1 to n: a plane goes on
    np.testing.assert_allclose(fine, 2.5 * xx - 1.5 * yy + 7.0, atol=1e-9)
    with pytest.raises(ValueError, match="margin"):
        upsample2(h, margin=4)


def test_upsampling_follows_a_cubic_between_pixels() -> None:
    # a cubic B-spline interpolant reproduces cubics away from the border; bilinear misses the
    # curvature by f (1 - f) h'' / 2 at the half pixel
    yy, xx = np.mgrid[0:24, 0:24].astype(np.float64)
    cubic = lambda x, y: 0.01 * (x - 11.3) ** 3 - 0.05 * (y - 9.0) ** 2 + 0.2 * x * y  # noqa: E731
    fine = upsample2(cubic(xx, yy))
    fy, fx = np.mgrid[0:47, 0:47] / 2.0
    inner = (slice(16, 31), slice(16, 31))  # pixels 8-15: far from the border's guess
    np.testing.assert_allclose(fine[inner], cubic(fx, fy)[inner], atol=1e-3)


def test_upsampling_a_stack_is_upsampling_each_slice() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(2, 10, 14))
    both = upsample2(a)
    np.testing.assert_allclose(both[1], upsample2(a[1]), atol=1e-12)


def test_upsampling_leaves_holes_and_their_reach_nan_only() -> None:
    rng = np.random.default_rng(1)
    h = rng.normal(size=(20, 20))
    holed = h.copy()
    holed[10, 10] = np.nan
    fine, ref = upsample2(holed), upsample2(h)
    bad = np.argwhere(np.isnan(fine))
    # the spline's support around the hole: a node within a pixel of it (17-23 in nodes)
    assert bad.min() == 17 and bad.max() == 23
    far = np.ones_like(fine, dtype=bool)
    far[12:29, 12:29] = False
    np.testing.assert_allclose(fine[far], ref[far], atol=0.02)


def test_looked_up_slope_noise_is_known() -> None:
    # bilinear between central differences: 1/3 across (their mean square) x 2/3 along
    assert slope_noise(1) == pytest.approx(2.0 / 9.0, rel=1e-3)
    # between spline nodes: measured on white noise
    rng = np.random.default_rng(2)
    u = rng.uniform(4.0, 24.0, 400)
    v = rng.uniform(4.0, 24.0, 400)
    seen = []
    for _ in range(200):
        gx = np.gradient(rng.normal(size=(30, 30)), axis=1)
        fine = upsample2(gx)
        (val,), _ = bilinear([fine], 2 * v, 2 * u)
        seen.append(val**2)
    assert slope_noise(2) == pytest.approx(float(np.mean(seen)), rel=0.05)
    with pytest.raises(ValueError, match="nodes per pixel"):
        slope_noise(3)
