"""Simultaneous least squares of per-patch offsets from pairwise differences.

Every overlapping pair ``(a, b)`` measures ``x_a - x_b`` with an information matrix (or a scalar
weight); all patches are solved at once (never chained), with robust re-weighting so that a wrong
pairwise measurement is outvoted by the loops of the grid. Each connected group of patches gets
its own gauge: its mean offset is zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from merge.core.progress import checkpoint
from merge.core.sparse import solve_symmetric

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Robust factor of a pair taken for right (``honoured``): its measurement then holds to a
#: hundredth of its own uncertainty against the rest.
HONOURED = 1e4


@dataclass(frozen=True)
class NetworkSolution:
    """Offsets ``x`` (n, d), robust factor per pair (k,), residuals (k, d), components (n,),
    and the residual scale the last robust round weighed them by (Mahalanobis units)."""

    x: FloatArray
    robust: FloatArray
    residuals: FloatArray
    component: IntArray
    scale: float = 1.0


def solve_pair_differences(
    n: int,
    pairs: IntArray,
    measured: FloatArray,
    weights: FloatArray,
    *,
    scale_floor: float = 1.0,
    robust_iterations: int = 8,
    prior: float = 0.0,
    honoured: int | None = None,
    scale: float | None = None,
) -> NetworkSolution:
    """Solve ``x_a - x_b = m_ab`` for all pairs in the weighted, robust least-squares sense.

    Parameters
    ----------
    n : int
        Number of patches.
    pairs : (k, 2) int array
        Patch indices ``(a, b)``.
    measured : (k,) or (k, d) array
        Measured differences ``x_a - x_b``.
    weights : (k,) or (k, d, d) array
        Information (inverse variance, or inverse covariance matrix) of each measurement; 0
        drops a pair.
    scale_floor : float, keyword-only
        Smallest residual scale of the Cauchy re-weighting, in standard deviations of the
        measurements (the Mahalanobis distance ``sqrt(r' W r)``).
    robust_iterations : int, keyword-only
        Iteratively re-weighted least-squares rounds (0 for plain least squares).
    prior : float, keyword-only
        Information (1 / σ²) of a prior holding every offset near zero. Directions no pair
        measures (the stripes of a 1-D grating, a flat overlap) then stay at zero instead of
        being left to round-off; 0 leaves only a numerical regulariser.
    honoured : int, keyword-only
        A pair taken for right, whatever the others say: its robust factor stays
        :data:`HONOURED` through every round, so the loops it breaks weigh down the pairs
        that disagree with it instead (a hypothesis, :mod:`merge.start.hypotheses`). Its
        ``robust`` is then that factor.
    scale : float, keyword-only
        A residual scale (Mahalanobis units) held through every round instead of the one the
        residuals' median sets (and ``scale_floor``): hypotheses judged by one measure of
        agreement (a pair taken for right deforms the least-squares solution all around it,
        and the median would grow with it until nothing disagrees).
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    m = np.asarray(measured, dtype=np.float64)
    if m.ndim == 1:
        m = m[:, None]
    k, d = m.shape
    w_in = np.asarray(weights, dtype=np.float64)
    W0 = w_in[:, None, None] * np.eye(d)[None] if w_in.ndim == 1 else w_in
    if len(pairs) != k or W0.shape != (k, d, d):
        raise ValueError("pairs, measured and weights must describe the same pairs")
    if not np.isfinite(W0).all():
        raise ValueError("weights must be finite")
    tr = np.trace(W0, axis1=1, axis2=2)
    if (tr < 0).any():
        raise ValueError("weights must be non-negative")
    use = tr > 0
    # the factorisations take the pairs with information only: the others add nothing but
    # structure, and fill (10,000 patches: two thirds of the first pass's pairs; without them,
    # and without pivoting (merge.core.sparse), a round took 0.14 s instead of 0.55)
    kept = np.flatnonzero(use)
    graph = coo_matrix((np.ones(int(use.sum())), (pairs[use, 0], pairs[use, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    if honoured is not None and not 0 <= honoured < k:
        raise ValueError(f"honoured must index a pair (0 to {k - 1}), got {honoured}")
    factor = np.ones(k)
    if honoured is not None:
        factor[honoured] = HONOURED
    x = np.zeros((n, d))
    res = m.copy()
    if scale is not None and not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    spread = scale_floor if scale is None else scale
    for it in range(robust_iterations + 1):
        checkpoint()  # a round of 10,000 patches takes a second
        x = _solve(n, pairs[kept], m[kept], W0[kept] * factor[kept, None, None], prior)
        res = m - (x[pairs[:, 0]] - x[pairs[:, 1]])
        if it == robust_iterations or not use.any():
            break
        r = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", res, W0, res), 0.0))
        if scale is None:
            spread = max(1.4826 * float(np.median(r[use])), scale_floor)
        factor = 1.0 / (1.0 + (r / (2.5 * spread)) ** 2)
        if honoured is not None:
            factor[honoured] = HONOURED
    return NetworkSolution(
        x=x, robust=factor, residuals=res, component=comp.astype(np.intp), scale=spread
    )


def _solve(
    n: int,
    pairs: IntArray,
    m: FloatArray,
    W: FloatArray,
    prior: float,
) -> FloatArray:
    k, d = m.shape
    a, b = pairs[:, 0], pairs[:, 1]
    ii, jj = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
    blocks = []
    for ra, cb, sign in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
        rows = (ra[:, None, None] * d + ii[None]).ravel()
        cols = (cb[:, None, None] * d + jj[None]).ravel()
        blocks.append((rows, cols, (sign * W).ravel()))
    rows = np.concatenate([blk[0] for blk in blocks])
    cols = np.concatenate([blk[1] for blk in blocks])
    vals = np.concatenate([blk[2] for blk in blocks])
    # Gauge. The right-hand side has no component along the null space of this block Laplacian
    # (one constant offset per connected group), so a small Tikhonov term (or the prior) makes
    # the system regular and leaves every group with zero mean offset; an isolated patch stays 0.
    scale = float(np.abs(W).max()) if k else 1.0
    eps = max(prior, 1e-9 * (scale if scale > 0 else 1.0))
    diag = np.arange(n * d)
    system = coo_matrix(
        (
            np.concatenate([vals, np.full(n * d, eps)]),
            (np.concatenate([rows, diag]), np.concatenate([cols, diag])),
        ),
        shape=(n * d, n * d),
    ).tocsc()
    rhs = np.zeros(n * d)
    wm = np.einsum("kij,kj->ki", W, m)
    np.add.at(rhs, (a[:, None] * d + np.arange(d)).ravel(), wm.ravel())
    np.add.at(rhs, (b[:, None] * d + np.arange(d)).ravel(), -wm.ravel())
    out: FloatArray = solve_symmetric(system, rhs).reshape(n, d)
    return out
