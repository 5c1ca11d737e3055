import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.paper.shape_index import principal_curvatures, shape_index

N = 41
SPACING = 1e-8
_y, _x = (np.mgrid[0:N, 0:N] - N // 2) * SPACING
CURV = 2e6  # 1/m: a radius of 500 nm


@pytest.mark.parametrize(
    ("surface", "expected"),
    [
        (-0.5 * CURV * (_x**2 + _y**2), 1.0),  # cap (dome)
        (0.5 * CURV * (_x**2 + _y**2), -1.0),  # cup
        (0.5 * CURV * (_x**2 - _y**2), 0.0),  # symmetric saddle
        (-0.5 * CURV * _x**2, 0.5),  # ridge
        (0.5 * CURV * _x**2, -0.5),  # valley (rut)
        (0.0 * _x + 3e-9 * _y, 0.0),  # tilted plane: flat by decision
    ],
)
def test_analytic_surfaces(surface: np.ndarray, expected: float) -> None:
    si = shape_index(surface, SPACING, noise=0.0)
    assert si[N // 2, N // 2] == pytest.approx(expected, abs=0.02)


def test_curvatures_of_a_sphere_include_the_slope_terms() -> None:
    r = 1e-6
    z = np.sqrt(r**2 - _x**2 - _y**2)  # a sphere cap: |k| = 1/r everywhere, slopes included
    k1, k2 = principal_curvatures(z, SPACING, smooth=0.0)
    inner = (slice(N // 2 - 10, N // 2 + 10),) * 2
    np.testing.assert_allclose(k1[inner], -1 / r, rtol=0.02)
    np.testing.assert_allclose(k2[inner], -1 / r, rtol=0.02)


def test_noise_on_a_plateau_is_flat_and_nan_is_kept() -> None:
    rng = np.random.default_rng(1)
    h = rng.normal(0, 1e-9, (N, N))
    h[3, 3] = np.nan
    si = shape_index(h, 2e-8)
    assert np.isnan(si[3, 3])
    assert np.mean(si[np.isfinite(si)] == 0.0) > 0.9


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.5, 3.0))
def test_range_and_sign_symmetry(seed: int, amplitude: float) -> None:
    rng = np.random.default_rng(seed)
    from scipy.ndimage import gaussian_filter

    h = gaussian_filter(rng.normal(size=(32, 32)), 3) * amplitude * 1e-7
    si = shape_index(h, SPACING, noise=0.0)
    assert np.all((si >= -1) & (si <= 1))
    # turning the surface upside down swaps caps and cups
    np.testing.assert_allclose(shape_index(-h, SPACING, noise=0.0), -si, atol=1e-9)
