"""Diagonal blocks of the inverse of a large sparse symmetric positive definite matrix, without
the inverse.

The marginal covariance of every patch is a diagonal block of the inverse information matrix.
Solving for it column by column costs as many solves as unknowns, time and memory growing as
the square of the mosaic (1,600 patches: 22 s; 10,000 would need 14 GB for the right-hand sides
alone). The units (patches) are cut instead into slabs, in an order along the mosaic, so that
each slab couples only to the slab before and the one after: the matrix is then
block-tridiagonal, and two sweeps over the slabs give every diagonal block exactly (the
recursion of Takahashi, as the recursive Green's function method runs it):

- forward, the Schur complements ``g_k = (D_k - L_k g_(k-1) L_k')⁻¹``;
- backward, ``G_kk = g_k + g_k U_k G_(k+1)(k+1) U_k' g_k``, from the last slab's ``G = g``.

Each step is dense in a slab (a row of patches across a square mosaic: for 100 x 100 patches,
600 unknowns), so the time grows as the number of slabs times a slab's size cubed, and the
memory as one slab's size squared per slab.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import LinAlgError, lapack
from scipy.sparse import csr_matrix, spmatrix
from scipy.sparse.csgraph import reverse_cuthill_mckee

from merge.core.progress import checkpoint

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def slabs(pairs: IntArray, n: int, order: IntArray | None = None) -> list[IntArray]:
    """Cut ``n`` units, linked by ``pairs`` (k, 2), into slabs where every link joins one
    slab to itself or to the next.

    ``order`` (n,): the units in the order to cut them (along the mosaic's longer axis keeps
    the slabs small); default a reverse Cuthill-McKee order of the links. Greedy: each slab
    reaches as far as the links of the slab before it reach.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    if order is None:
        graph = csr_matrix(
            (np.ones(2 * len(pairs)), (pairs.ravel(), pairs[:, ::-1].ravel())), shape=(n, n)
        )
        order = np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), dtype=np.intp)
    order = np.asarray(order, dtype=np.intp)
    if sorted(order.tolist()) != list(range(n)):
        raise ValueError(f"order must hold every unit 0..{n - 1} once")
    position = np.empty(n, dtype=np.intp)
    position[order] = np.arange(n)
    # the farthest position (in the order) each unit links to, its own at least
    reach = position.copy()
    if len(pairs):
        np.maximum.at(reach, pairs[:, 0], position[pairs[:, 1]])
        np.maximum.at(reach, pairs[:, 1], position[pairs[:, 0]])
    far = reach[order]  # by position
    bounds = [0]
    end = 1 if n else 0
    while end < n:
        bounds.append(end)
        # the next slab holds everything the current one links to
        end = max(end + 1, int(far[bounds[-2] : end].max()) + 1)
    bounds.append(n)
    return [order[lo:hi] for lo, hi in pairwise(bounds) if hi > lo]


def _inverse(D: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive definite ``D`` (Cholesky); LU if it is not."""
    c, info = lapack.dpotrf(D, lower=False)
    if info == 0:
        inv, info = lapack.dpotri(c, lower=False)
        if info == 0:
            upper = np.triu(inv)
            out: FloatArray = upper + np.triu(inv, 1).T
            return out
    try:
        lu: FloatArray = np.asarray(np.linalg.inv(D), dtype=np.float64)
    except np.linalg.LinAlgError as exc:
        raise LinAlgError(f"a slab of the matrix is singular: {exc}") from None
    return lu


def diagonal_blocks(
    M: spmatrix, size: int, parts: list[IntArray] | None = None, *, pairs: IntArray | None = None
) -> FloatArray:
    """The ``size`` x ``size`` diagonal blocks ``(n, size, size)`` of ``M⁻¹``.

    Parameters
    ----------
    M : sparse (size n, size n)
        Symmetric positive definite; unit ``u`` holds rows ``size u .. size u + size - 1``.
    size : int
        Unknowns per unit.
    parts : list of (k,) int arrays, optional
        The slabs (:func:`slabs`); default cut from ``M``'s own links (``pairs`` if given).
    """
    if size < 1 or M.shape[0] != M.shape[1] or M.shape[0] % size:
        raise ValueError(f"M must be square in whole units of {size}, got shape {M.shape}")
    n = M.shape[0] // size
    if parts is None:
        if pairs is None:
            coo = M.tocoo()
            pairs = np.column_stack([coo.row // size, coo.col // size])
            pairs = pairs[pairs[:, 0] < pairs[:, 1]]
        parts = slabs(pairs, n)
    unknowns = [(p[:, None] * size + np.arange(size)).ravel() for p in parts]
    csr = csr_matrix(M)
    out = np.zeros((n, size, size))
    schur: list[FloatArray] = []
    # M between slab k and slab k + 1, sparse: a unit links to a few of the next slab's, so
    # products with it cost a few of its rows each, not a dense product (100 x 100 patches:
    # 4.0 -> 2.6 s)
    couplings: list[csr_matrix] = []
    for k, rows in enumerate(unknowns):
        checkpoint()
        band = csr[rows]
        D = band[:, rows].toarray()
        if k:
            U = couplings[k - 1]  # (previous slab, this one)
            SU = np.asarray(U.T @ schur[k - 1])  # U' g, dense
            D -= np.asarray(U.T @ SU.T)  # U' g U (g symmetric)
        if k + 1 < len(unknowns):
            couplings.append(csr_matrix(band[:, unknowns[k + 1]]))
        schur.append(_inverse(D))
    G = schur[-1]
    _put(out, parts[-1], G, size)
    for k in range(len(parts) - 2, -1, -1):
        checkpoint()
        X = np.asarray((couplings[k].T @ schur[k]).T)  # g_k U_k (g_k symmetric)
        G = schur[k] + X @ G @ X.T
        schur[k + 1] = np.empty(0)  # the memory goes back slab by slab
        couplings[k] = csr_matrix((0, 0))
        _put(out, parts[k], G, size)
    return out


def _put(out: FloatArray, units: IntArray, G: FloatArray, size: int) -> None:
    """The diagonal blocks of a slab's ``G`` into ``out`` at its units."""
    m = len(units)
    blocks = G.reshape(m, size, m, size)[np.arange(m), :, np.arange(m), :]
    out[units] = blocks
