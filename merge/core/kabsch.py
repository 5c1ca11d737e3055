"""Weighted least-squares rigid transform between corresponding point sets."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def weighted_rigid_transform(
    source: FloatArray, target: FloatArray, weights: FloatArray | None = None
) -> tuple[FloatArray, FloatArray]:
    """Rotation ``R`` and translation ``t`` minimising ``Σ w_i |R s_i + t - q_i|²``.

    Weighted Kabsch/Umeyama without scale: the weights enter the centroids and the
    cross-covariance; a reflection is never returned (the smallest singular direction is flipped
    when the determinant is negative).

    Parameters
    ----------
    source, target : (m, d) arrays
        Corresponding points, ``d`` = 2 or 3.
    weights : (m,) array, optional
        Non-negative weights; uniform when not given.

    Returns
    -------
    R : (d, d) array
    t : (d,) array
    """
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    if p.ndim != 2 or p.shape != q.shape:
        raise ValueError(f"source and target must both be (m, d), got {p.shape} and {q.shape}")
    m, d = p.shape
    if d not in (2, 3):
        raise ValueError(f"points must be 2-D or 3-D, got d = {d}")
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (m,):
        raise ValueError(f"weights must have shape ({m},), got {w.shape}")
    if not np.all(np.isfinite(w)) or (w < 0).any():
        raise ValueError("weights must be finite and non-negative")
    if np.count_nonzero(w) < d:
        raise ValueError(
            f"need at least {d} points with positive weight, got {np.count_nonzero(w)}"
        )
    wsum = w.sum()
    pc = (w @ p) / wsum
    qc = (w @ q) / wsum
    cov = (p - pc).T @ ((q - qc) * w[:, None])
    u, _, vt = np.linalg.svd(cov)
    flip = np.eye(d)
    flip[-1, -1] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    R = vt.T @ flip @ u.T
    t = qc - R @ pc
    return R, t
