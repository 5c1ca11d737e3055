"""The mosaic's sparse system from its runs' blocks: every run's source block, mapped onto its
two patches, and the blocks that scan lines shared between runs of one source put between them.

A run's rows see only the relative unknowns ``y = x_a - T' x_b`` of its source ``a`` and
destination ``b`` (:func:`relative_maps`), so one 6 x 6 block per run (in ``y``) gives all four
of its blocks in the patches' unknowns; :func:`assemble` sums them where they meet.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from merge.core.progress import checkpoint
from merge.core.sparse import sum_at
from merge.refine.bank import SurfaceBank
from merge.refine.lines import SharedLines
from merge.refine.rows import PatchState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def assemble(
    bank: SurfaceBank,
    state: PatchState,
    a_seg: IntArray,
    b_seg: IntArray,
    Baa: FloatArray,
    ga: FloatArray,
    shared: SharedLines,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """Triplets of ``A``, ``g`` and the diagonal blocks from every run's source block and the
    blocks ``shared`` between runs of one source.

    Within one directed pair the destination's Jacobian is a fixed linear map of the source's,
    ``Jb = -T Ja`` (rotations about z): its spin arm is the source's plus ``Δ = s_a - s_b``,
    and its plane arm ``(x', y') = M (x_a, y_a) + c`` with ``M = [R_b' R_a]_xy`` and
    ``c = [R_b' Δ]_xy``. A run's rows see the relative unknowns ``y = x_a - T' x_b``, so a
    block ``C`` between runs ``k`` and ``l`` of source ``a`` is ``-C`` on ``y_k' y_l``: on
    ``(a, a)``, ``(a, b_l)``, ``(b_k, a)`` and ``(b_k, b_l)`` through ``T_k`` and ``T_l``
    (two destinations of one source coupled where one of its lines crosses both).
    """
    n = len(bank.centre)
    T = relative_maps(bank, state, a_seg, b_seg)
    Tt = np.swapaxes(T, 1, 2)
    Bbb = T @ Baa @ Tt
    Bab = -(Baa @ Tt)
    Tga = np.einsum("kij,kj->ki", T, ga)
    g = sum_at(np.concatenate([a_seg, b_seg]), np.concatenate([-ga, Tga]), n)
    # blocks (row patch, column patch) off the diagonal: every run's, and the three of each pair
    # of runs sharing lines (``y_one' M y_other``, ``M = -C``)
    one, other = shared.first, shared.second
    M = -shared.C
    diag = sum_at(
        np.concatenate([a_seg, b_seg, a_seg[one]]),
        np.concatenate([Baa, Bbb, M + np.swapaxes(M, 1, 2)]),
        n,
    )
    parts: list[tuple[IntArray, IntArray, Callable[[], FloatArray]]] = [
        (a_seg, b_seg, lambda: Bab),
        (a_seg[one], b_seg[other], lambda: -(M @ Tt[other])),
        (b_seg[one], a_seg[one], lambda: -(T[one] @ M)),
        (b_seg[one], b_seg[other], lambda: T[one] @ M @ Tt[other]),
    ]
    # one block per patch (its diagonal) and one per pair of patches above the diagonal, with its
    # transpose below: the blocks summed where they meet (both directions of a pair fall on the
    # same two places), a third of the triplets of four per run; a part's blocks made when they
    # are summed (a large mosaic's pairs of runs hold tens of megabytes of them)
    keys = [np.minimum(r, c) * n + np.maximum(r, c) for r, c, _ in parts]
    pair, at = np.unique(np.concatenate(keys), return_inverse=True)
    checkpoint()  # each of these steps takes a few tenths of a second on 10,000 patches
    off = np.zeros((len(pair), 6, 6))
    start = 0
    for (r, c, made), key in zip(parts, keys, strict=True):
        where, start = at[start : start + len(key)], start + len(key)
        blocks, below = made(), r > c
        blocks[below] = np.swapaxes(blocks[below], 1, 2)  # a fresh array: each part's own
        off += sum_at(where, blocks, len(pair))
        checkpoint()
    first, second = pair // n, pair % n
    a_rows, a_cols, vals = _block_triplets(
        (np.arange(n), np.arange(n), diag),
        (first, second, off),
        (second, first, np.swapaxes(off, 1, 2)),
    )
    return (
        a_rows,
        a_cols,
        vals,
        g,
        diag,
    )


def relative_maps(
    bank: SurfaceBank, state: PatchState, a_seg: IntArray, b_seg: IntArray
) -> FloatArray:
    """``T`` (k, 6, 6) of every run from source ``a_seg`` to destination ``b_seg`` (k,): a row's
    Jacobian on the destination's unknowns is ``-T`` times its Jacobian on the source's, so the
    run sees only ``y = x_a - T' x_b`` (:func:`assemble`)."""
    R, s = state.R, state.s
    rho_a, rho_b = bank.radius[a_seg], bank.radius[b_seg]
    delta = s[a_seg] - s[b_seg]
    RbRa = np.einsum("kji,kjl->kil", R[b_seg], R[a_seg])
    c = np.einsum("kji,kj->ki", R[b_seg], delta)
    T = np.zeros((len(a_seg), 6, 6))
    T[:, [0, 1, 2], [0, 1, 2]] = 1.0
    T[:, 3, 0], T[:, 3, 1], T[:, 3, 3] = -delta[:, 1] / rho_b, delta[:, 0] / rho_b, rho_a / rho_b
    for row, k in ((4, 0), (5, 1)):
        T[:, row, 2] = c[:, k] / rho_b
        T[:, row, 4] = RbRa[:, k, 0] * rho_a / rho_b
        T[:, row, 5] = RbRa[:, k, 1] * rho_a / rho_b
    return T


def _block_triplets(
    *parts: tuple[IntArray, IntArray, FloatArray],
) -> tuple[IntArray, IntArray, FloatArray]:
    """Triplets of 6 x 6 blocks: per part the block rows (k,), block columns (k,) and blocks
    (k, 6, 6)."""
    size = sum(36 * len(r) for r, _, _ in parts)
    rows, cols = np.empty(size, dtype=np.intp), np.empty(size, dtype=np.intp)
    vals = np.empty(size)
    ii, jj = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    start = 0
    for r, c, blk in parts:
        k = len(r)
        at = slice(start, start + 36 * k)
        rows[at].reshape(k, 6, 6)[:] = r[:, None, None] * 6 + ii
        cols[at].reshape(k, 6, 6)[:] = c[:, None, None] * 6 + jj
        vals[at].reshape(k, 6, 6)[:] = blk
        start += 36 * k
    return rows, cols, vals
