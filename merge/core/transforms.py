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
    k = np.zeros((*w.shape[:-1], 3, 3))
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


class PatchTransform:
    """``T_mosaic_patch`` of the merge: a rigid motion plus a Z plane (the in-patch drift).

    ``q = R p + t + e_z · (slope · (p_xy - centre))`` for nominal patch points ``p = (x, y, z)``
    (metres). The plane is the linear Z drift a patch picked up while it was scanned; it moves
    heights only, never XY, so a drift is not mistaken for a tilt that would shear the top of a
    step against its foot.

    Attributes
    ----------
    R : (3, 3) rotation
    t : (3,) translation, metres
    slope : (2,) dz/dx and dz/dy of the drift plane (dimensionless)
    centre : (2,) nominal XY where the drift plane is zero, metres
    """

    __slots__ = ("R", "centre", "slope", "t")

    def __init__(
        self,
        R: FloatArray | None = None,
        t: FloatArray | None = None,
        slope: FloatArray | None = None,
        centre: FloatArray | None = None,
    ) -> None:
        self.R = np.eye(3) if R is None else np.asarray(R, dtype=np.float64).reshape(3, 3)
        self.t = np.zeros(3) if t is None else np.asarray(t, dtype=np.float64).reshape(3)
        self.slope = (
            np.zeros(2) if slope is None else np.asarray(slope, dtype=np.float64).reshape(2)
        )
        self.centre = (
            np.zeros(2) if centre is None else np.asarray(centre, dtype=np.float64).reshape(2)
        )

    def apply(self, points: FloatArray) -> FloatArray:
        """Map ``(m, 3)`` nominal patch points to the mosaic frame."""
        p = np.asarray(points, dtype=np.float64)
        q = p @ self.R.T + self.t
        q[:, 2] += (p[:, :2] - self.centre) @ self.slope
        return q

    def rigid_approximation(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The rigid ``(R, t)`` closest to this transform over ``points`` (least squares).

        For consumers that only understand rigid transforms: the drift plane becomes the tilt
        that best reproduces it on these points.
        """
        from merge.core.kabsch import weighted_rigid_transform

        p = np.asarray(points, dtype=np.float64)
        if not self.slope.any():
            return self.R.copy(), self.t.copy()
        return weighted_rigid_transform(p, self.apply(p))

    def __repr__(self) -> str:
        return (
            f"PatchTransform(R={self.R.tolist()}, t={self.t.tolist()}, slope={self.slope.tolist()})"
        )
