import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from merge.core.kabsch import weighted_rigid_transform
from merge.core.transforms import rotation_from_vector


@settings(max_examples=50, deadline=None)
@given(
    arrays(np.float64, 3, elements=st.floats(-3, 3)),
    arrays(np.float64, 3, elements=st.floats(-1e-6, 1e-6)),
    st.integers(0, 1000),
)
def test_recovers_a_known_transform(omega: np.ndarray, t: np.ndarray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(20, 3)) * 1e-6
    R = rotation_from_vector(omega)
    q = p @ R.T + t
    w = rng.uniform(0.1, 2.0, 20)
    R_est, t_est = weighted_rigid_transform(p, q, w)
    np.testing.assert_allclose(R_est, R, atol=1e-8)
    np.testing.assert_allclose(t_est, t, atol=1e-13)
    assert np.linalg.det(R_est) == pytest.approx(1.0)


def test_weights_enter_the_covariance() -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=(30, 3))
    q = p + [1.0, 2.0, 3.0]
    q[:5] += rng.normal(size=(5, 3)) * 50  # outliers with zero weight do not count
    w = np.ones(30)
    w[:5] = 0
    R, t = weighted_rigid_transform(p, q, w)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-10)
    np.testing.assert_allclose(t, [1, 2, 3], atol=1e-10)


def test_never_returns_a_reflection() -> None:
    # a mirrored planar configuration: the unconstrained optimum is a reflection
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=float)
    q = p * [1, -1, 1]
    R, _ = weighted_rigid_transform(p, q)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_two_dimensional_points() -> None:
    a = 0.3
    R2 = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    p = np.random.default_rng(0).normal(size=(6, 2))
    R, t = weighted_rigid_transform(p, p @ R2.T + [1, -1])
    np.testing.assert_allclose(R, R2, atol=1e-12)
    np.testing.assert_allclose(t, [1, -1], atol=1e-12)


@pytest.mark.parametrize(
    ("p", "q", "w", "msg"),
    [
        (np.zeros((4, 3)), np.zeros((5, 3)), None, "both be"),
        (np.zeros((4, 4)), np.zeros((4, 4)), None, "2-D or 3-D"),
        (np.zeros((4, 3)), np.zeros((4, 3)), -np.ones(4), "non-negative"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.array([1.0, 1, 0, 0]), "at least 3"),
    ],
)
def test_bad_input(p: np.ndarray, q: np.ndarray, w: np.ndarray | None, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        weighted_rigid_transform(p, q, w)
