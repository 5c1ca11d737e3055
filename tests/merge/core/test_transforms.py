import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from merge.core.transforms import (
    PatchTransform,
    compose,
    invert,
    orthonormalize,
    rotation_about_z,
    rotation_angle_deg,
    rotation_from_vector,
)


@settings(max_examples=50, deadline=None)
@given(arrays(np.float64, 3, elements=st.floats(-4, 4)))
def test_rodrigues_gives_rotations(omega: np.ndarray) -> None:
    R = rotation_from_vector(omega)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    R_inv, t_inv = invert(R, np.array([1.0, 2.0, 3.0]))
    R_id, t_id = compose(R, np.array([1.0, 2.0, 3.0]), R_inv, t_inv)
    np.testing.assert_allclose(R_id, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t_id, 0, atol=1e-12)


def test_small_angles_and_about_z() -> None:
    np.testing.assert_allclose(rotation_from_vector(np.array([0, 0, 1e-10])), np.eye(3), atol=1e-9)
    np.testing.assert_allclose(rotation_from_vector(np.array([0, 0, 0.2])), rotation_about_z(0.2))
    assert rotation_angle_deg(rotation_about_z(np.radians(3))) == pytest.approx(3)
    noisy = rotation_about_z(0.1) + 1e-3
    np.testing.assert_allclose(
        orthonormalize(noisy) @ orthonormalize(noisy).T, np.eye(3), atol=1e-12
    )


def test_patch_transform_moves_heights_only_with_its_plane() -> None:
    tr = PatchTransform(
        rotation_about_z(0.01),
        np.array([1e-7, 0, 5e-9]),
        slope=np.array([1e-3, 0.0]),
        centre=np.array([1e-6, 0.0]),
    )
    p = np.array([[1e-6, 0, 0], [2e-6, 0, 0]])
    q = tr.apply(p)
    rigid = p @ tr.R.T + tr.t
    np.testing.assert_allclose(q[:, :2], rigid[:, :2])  # XY untouched by the drift plane
    assert q[1, 2] - rigid[1, 2] == pytest.approx(1e-9)


def test_rigid_approximation_reproduces_a_plane_as_a_tilt() -> None:
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(0, 1e-6, 500), rng.uniform(0, 1e-6, 500), np.zeros(500)])
    tr = PatchTransform(slope=np.array([0.0, 2e-3]), centre=np.array([5e-7, 5e-7]))
    R, t = tr.rigid_approximation(p)
    np.testing.assert_allclose(p @ R.T + t, tr.apply(p), atol=1e-11)  # second order: θ² L
    R0, _ = PatchTransform().rigid_approximation(p)
    np.testing.assert_array_equal(R0, np.eye(3))
