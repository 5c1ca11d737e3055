"""Rigid transforms ``q = R p + t`` held as arrays, one per patch.

Naming follows the frames: ``T_mosaic_patch`` maps nominal patch coordinates (stage frame,
metres) to the mosaic frame. Stacks of transforms are ``R`` of shape ``(n, 3, 3)`` and ``t`` of
shape ``(n, 3)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def rotation_from_vector(omega: FloatArray) -> FloatArray:
    """Rotation matrices from rotation vectors (Rodrigues).

    Parameters
    ----------
    omega : (..., 3) array
        Axis times angle, radians.

    Returns
    -------
    (..., 3, 3) array
    """
    w = np.asarray(omega, dtype=np.float64)
    if w.shape[-1] != 3:
        raise ValueError(f"rotation vectors need a last axis of 3, got shape {w.shape}")
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = np.zeros(w.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -w[..., 2], w[..., 1]
    k[..., 1, 0], k[..., 1, 2] = w[..., 2], -w[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -w[..., 1], w[..., 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    eye = np.broadcast_to(np.eye(3), k.shape)
    out: FloatArray = eye + a * k + b * (k @ k)
    return out


def rotation_about_z(angle: float) -> FloatArray:
    """The 3 x 3 rotation by ``angle`` radians about the z axis."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def apply(R: FloatArray, t: FloatArray, points: FloatArray) -> FloatArray:
    """``R @ p + t`` for points of shape ``(m, 3)`` with one transform ``R (3, 3)``, ``t (3,)``."""
    out: FloatArray = points @ R.T + t
    return out


def invert(R: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The inverse of ``q = R p + t`` (works on stacks)."""
    Rt = np.swapaxes(R, -1, -2)
    ti = -np.einsum("...ij,...j->...i", Rt, t)
    return Rt, ti


def compose(
    R_ab: FloatArray, t_ab: FloatArray, R_bc: FloatArray, t_bc: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``T_ac = T_ab ∘ T_bc`` (works on stacks)."""
    R = R_ab @ R_bc
    t = np.einsum("...ij,...j->...i", R_ab, t_bc) + t_ab
    return R, t


def orthonormalize(R: FloatArray) -> FloatArray:
    """Project (stacks of) near-rotation matrices back onto SO(3)."""
    u, _, vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, -1] *= d[..., None]
    out: FloatArray = u @ vt
    return out


def rotation_angle_deg(R: FloatArray) -> FloatArray:
    """Rotation angle of (stacks of) rotation matrices, degrees."""
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    out: FloatArray = np.degrees(np.arccos(c))
    return out
