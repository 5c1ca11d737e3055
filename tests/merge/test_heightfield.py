"""Height maps as surfaces: NaN-aware smoothing, slopes and bilinear look-ups."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from merge.heightfield import bilinear, slopes, smooth_nan

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


def test_slopes_and_bilinear_are_exact_on_a_plane() -> None:
    h = _plane()
    gx, gy = slopes(h, (2.0, 0.5))
    np.testing.assert_allclose(gx, 1.25)
    np.testing.assert_allclose(gy, -3.0)
    (val,), ok = bilinear([h], np.array([0.0, 3.25, 23.0, 23.5]), np.array([0.0, 7.5, 31.0, 2.0]))
    np.testing.assert_array_equal(ok, [True, True, True, False])
    expected = [7.0, 2.5 * 7.5 - 1.5 * 3.25 + 7.0, 2.5 * 31.0 - 1.5 * 23.0 + 7.0]
    np.testing.assert_allclose(val[:3], expected)
