"""The Gauss-Newton normal system of the default method (solved by :mod:`merge.refine.solve`).

Every row is one point of a source patch over a destination patch: its residual is the height
of the point above the destination's surface (drift plane included), linearised on the surface's
tangent plane, and re-weighted with a Cauchy function of the robust residual scale. Heights are
what the noise is in, so a residual on a steep flank counts as much as one on a terrace:
weighting them to distances along the normal (``1 / (1 + |slope|²)``) discarded most of what
the flanks, where XY is measured, hold (TGX1 over 18 draws: map/floor mean 1.43 -> 1.37;
variations with 25-30 % overlaps, 2 nm noise, 1° rotations, square patches better by 5-11 %;
the 1-D grating's XY 2.0 -> 2.1 nm, its map as before).
All residuals of one source line share that line's offset; on the raw heights they are
marginalised as a random effect (:mod:`merge.refine.lines`), so line means are trusted no more than
the offsets allow.
Each patch has six unknowns, in pixel units: translation (3), spin about z times the patch
radius, and the drift plane times the radius. The system is sparse: one 6 x 6 block per patch and
per overlapping pair.

Rows come in runs, one per directed pair (source, destination). They are processed in blocks of
whole runs, so the temporaries stay a few megabytes however large the mosaic (large temporaries
cost page faults on every allocation, which dominated the time of 400-patch mosaics), and the
blocks are shared among the cores (:mod:`merge.core.parallel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.information import line_design, noise_share, psd_part
from merge.core.parallel import each
from merge.refine.bank import SurfaceBank
from merge.refine.lines import line_groups, marginalise_offsets, offset_ratio

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Candidates = tuple[IntArray, IntArray, IntArray, IntArray]

#: Rows per block of the system build (whole runs are kept together).
BLOCK_ROWS = 1 << 15


@dataclass
class PatchState:
    """Where every patch is, in pixel units: ``q = R p_local + s + e_z (slope · p_local_xy)``.

    ``R`` (n, 3, 3) rotations, ``s`` (n, 3) the mosaic position of each patch frame's origin,
    ``slope`` (n, 2) the drift plane (dz/dx, dz/dy) of each patch.
    """

    R: FloatArray
    s: FloatArray
    slope: FloatArray


@dataclass(frozen=True)
class NormalSystem:
    """The sparse system ``A x = g`` (6 unknowns per patch) and fit statistics.

    ``rows``, ``cols``, ``vals`` are the triplets of ``A``; ``g`` (n, 6); per patch ``count`` (n,)
    residuals that involve it, ``sq`` (n,) the sum of their squares as distances along the surface
    normal and ``diag`` (n, 6, 6) its own information block; ``rms`` and ``rscale`` (robust scale)
    of the residuals (heights), pixel units. ``signal_vals`` (if asked for) are the values of ``A``
    at the same triplets without the share that slopes of the noise contribute (see
    :func:`merge.core.information.noise_share`): the information the surfaces themselves carry;
    ``line_design`` (then too) how much the residuals of one scan line of a run move together
    (:func:`merge.core.information.line_design`).
    """

    rows: IntArray
    cols: IntArray
    vals: FloatArray
    g: FloatArray
    count: FloatArray
    sq: FloatArray
    diag: FloatArray
    rms: float
    rscale: float = 0.0
    signal_vals: FloatArray | None = None
    line_design: float = 1.0


def _blocks(starts: IntArray, rows: int) -> list[tuple[int, int]]:
    """Ranges ``[first, last)`` of runs holding about ``rows`` rows each (at least one run)."""
    out = []
    k = len(starts) - 1
    first = 0
    while first < k:
        last = int(np.searchsorted(starts, starts[first] + rows, side="right")) - 1
        last = min(max(last, first + 1), k)
        out.append((first, last))
        first = last
    return out


def build_normal_system(
    bank: SurfaceBank,
    cand: Candidates,
    state: PatchState,
    noise: float,
    *,
    block_rows: int = BLOCK_ROWS,
    signal: bool = False,
    lines: bool = True,
) -> NormalSystem:
    """The Gauss-Newton system over all correspondences, and per-patch statistics.

    Parameters
    ----------
    bank : SurfaceBank
        The patches of this level.
    cand : tuple of int arrays
        ``(src, dst, idx, starts)`` from :meth:`SurfaceBank.candidates`.
    state : PatchState
        Current placement of every patch.
    noise : float
        Height noise, pixel units: the least robust scale.
    block_rows : int, keyword-only
        Rows per block; changes memory and speed, never the result.
    signal : bool, keyword-only
        Also compute ``signal_vals`` (for uncertainties, not for steps).
    lines : bool, keyword-only
        Marginalise the offsets of scan lines (:mod:`merge.refine.lines`), their size measured on
        the residuals.
    """
    n = len(bank.centre)
    src, dst, idx, starts = cand
    empty_i = np.empty(0, dtype=np.intp)
    empty = NormalSystem(
        empty_i,
        empty_i,
        np.empty(0),
        np.zeros((n, 6)),
        np.zeros(n),
        np.zeros(n),
        np.zeros((n, 6, 6)),
        0.0,
    )
    if len(idx) == 0:
        return empty
    blocks = _blocks(starts, block_rows)
    # pass 1: residual, slopes and lever arm of every row; the robust scale needs all of them
    m = len(idx)
    r, valid, arm = np.empty(m), np.empty(m), np.empty((m, 2))
    grad = np.empty((m, 2))

    def residuals(block: tuple[int, int]) -> None:
        lo, hi = starts[block[0]], starts[block[1]]
        r[lo:hi], valid[lo:hi], grad[lo:hi], arm[lo:hi] = _residuals(
            bank, idx[lo:hi], dst[lo:hi], starts[block[0] : block[1] + 1] - lo, state
        )

    each(residuals, blocks)
    d = r
    ok = valid > 0
    used = np.abs(d[ok])
    if used.size == 0:
        return empty
    rscale = max(1.4826 * float(np.median(used)), noise)
    w = valid / (1.0 + (d / (3.0 * rscale)) ** 2)
    # the residuals of one source line share its offset (merge.refine.lines); no groups, no offsets
    line = bank.line[idx]
    groups = line_groups(starts, line) if lines else np.empty(0, dtype=np.intp)
    rho = offset_ratio(r, w, valid, groups)
    # pass 2: per run, the source's information block and gradient
    k = len(starts) - 1
    Baa, ga = np.empty((k, 6, 6)), np.empty((k, 6))

    def information(block: tuple[int, int]) -> None:
        first, last = block
        lo, hi = starts[first], starts[last]
        runs = starts[first : last + 1] - lo
        J = _jacobians(
            bank, idx[lo:hi], dst[lo:hi], runs, state, grad[lo:hi], ok[lo:hi], arm[lo:hi]
        )
        Baa[first:last], ga[first:last] = segment_sums(J, w[lo:hi], r[lo:hi], runs)
        g_lo, g_hi = np.searchsorted(groups, [lo, hi])
        marginalise_offsets(
            J,
            w[lo:hi],
            r[lo:hi],
            runs,
            groups[g_lo:g_hi] - lo,
            rho,
            Baa[first:last],
            ga[first:last],
        )

    each(information, blocks)
    a_seg, b_seg = src[starts[:-1]], dst[starts[:-1]]
    signal_blocks, design = None, 1.0
    if signal:
        pitch2 = 0.5 * (bank.dx[b_seg] ** -2 + bank.dy[b_seg] ** -2)
        share = noise_share(
            w, arm, starts, bank.radius[a_seg], bank.slope_noise * noise**2 * pitch2
        )
        signal_blocks = psd_part(Baa - share)
        # the design effect of the raw Z scores, on top of the offsets' model: measured on the
        # whitened scores (what the model leaves correlated) the Z sigmas were 1.3-1.9 x too
        # small on TGX1, its flat face and the grating (a bowl no line model holds); this way
        # they are 0.9-1.4 x, and cautious (0.3-0.6 x) on MoS2 and the folded surface
        design = line_design(w * r, starts, line)
    count = np.bincount(src[ok], minlength=n) + np.bincount(dst[ok], minlength=n)
    # reported per patch as distances along the normal: how far the surfaces lie apart (a flank
    # misplaced by a nanometre is tens of nanometres off in height)
    d2 = d**2 / (1.0 + np.einsum("ij,ij->i", grad, grad))
    sq = np.asarray(
        np.bincount(src, weights=d2, minlength=n) + np.bincount(dst, weights=d2, minlength=n),
        dtype=np.float64,
    )
    rows, cols, vals, g, diag = _assemble(bank, state, a_seg, b_seg, Baa, ga)
    signal_vals = None
    if signal_blocks is not None:
        signal_vals = _assemble(bank, state, a_seg, b_seg, signal_blocks, ga)[2]
    return NormalSystem(
        rows=rows,
        cols=cols,
        vals=vals,
        g=g,
        diag=diag,
        count=count.astype(np.float64),
        sq=sq,
        rms=float(np.sqrt(np.mean(used**2))),
        rscale=rscale,
        signal_vals=signal_vals,
        line_design=design,
    )


def _run_maps(state: PatchState, a: IntArray, b: IntArray) -> tuple[FloatArray, FloatArray]:
    """Per run: the affine map ``p_b = M p_a + c`` from the source's frame to the destination's.

    ``q = R_a p + s_a + e_z (slope_a · p_xy)`` in the mosaic, then ``p_b = R_b' (q - s_b)``:
    ``M = R_b' (R_a + e_z [slope_a, 0])`` (k, 3, 3) and ``c = R_b' (s_a - s_b)`` (k, 3).
    """
    A = state.R[a]  # a gathered copy
    A[:, 2, :2] += state.slope[a]
    M = np.einsum("kji,kjl->kil", state.R[b], A)
    c = np.einsum("kji,kj->ki", state.R[b], state.s[a] - state.s[b])
    return M, c


def _residuals(
    bank: SurfaceBank, idx: IntArray, dst: IntArray, starts: IntArray, state: PatchState
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per row: residual, validity (1 or 0), normal slopes (m, 2), lever arm (m, 2).

    Rows ``idx`` (points) over ``dst`` (patches) come in runs ``starts[k]:starts[k + 1]`` of one
    directed pair each, so every run moves its points with one small matrix product. The
    residual is the height of the source point above the destination's surface and drift plane;
    its gradient with respect to the mosaic position is the destination's normal
    ``(-slope_x, -slope_y, 1)``.
    """
    a, b = bank.owner[idx[starts[:-1]]], dst[starts[:-1]]
    M, c = _run_maps(state, a, b)
    p_src = bank.points[idx]
    p_dst = np.empty_like(p_src)
    arm = np.empty((len(idx), 2))
    Ra = state.R[a, :2, :]
    for k in range(len(a)):
        lo, hi = starts[k], starts[k + 1]
        np.matmul(p_src[lo:hi], M[k].T, out=p_dst[lo:hi])
        p_dst[lo:hi] += c[k]
        np.matmul(p_src[lo:hi], Ra[k].T, out=arm[lo:hi])
    h, gx, gy, ok = bank.lookup(dst, p_dst)
    slope = state.slope[dst]
    r = np.where(ok, p_dst[:, 2] - np.einsum("mi,mi->m", slope, p_dst[:, :2]) - h, 0.0)
    grad = np.column_stack([gx, gy]) + slope
    grad[~ok] = 0.0
    return r, ok.astype(np.float64), grad, arm


def _jacobians(
    bank: SurfaceBank,
    idx: IntArray,
    dst: IntArray,
    starts: IntArray,
    state: PatchState,
    grad: FloatArray,
    ok: NDArray[np.bool_],
    arm: FloatArray,
) -> FloatArray:
    """(m, 6) derivative of every residual with respect to its source patch's unknowns.

    The translation part is the destination's normal in the mosaic, ``R_b (-grad, 1)``: one
    rotation per run.
    """
    nrm = np.column_stack([-grad, ok.astype(np.float64)])
    m = np.empty_like(nrm)
    for k, b in enumerate(dst[starts[:-1]]):
        lo, hi = starts[k], starts[k + 1]
        np.matmul(nrm[lo:hi], state.R[b].T, out=m[lo:hi])
    rho = bank.radius[bank.owner[idx], None]
    spin = (m[:, 1] * arm[:, 0] - m[:, 0] * arm[:, 1])[:, None]
    return np.concatenate([m, spin / rho, bank.points[idx, :2] / rho], axis=1)


def segment_sums(
    J: FloatArray, w: FloatArray, r: FloatArray, starts: IntArray
) -> tuple[FloatArray, FloatArray]:
    """Per run of rows ``starts[k]:starts[k + 1]``: ``Σ w J J'`` (k, 6, 6) and ``Σ w r J`` (k, 6).

    ``J`` (m, 6), ``w`` and ``r`` (m,); runs are non-empty and cover the rows from
    ``starts[0]`` on. One matrix product per run (runs hold hundreds of rows).
    """
    k = len(starts) - 1
    B, grad = np.empty((k, 6, 6)), np.empty((k, 6))
    wJ = J * w[:, None]
    for j in range(k):
        lo, hi = starts[j], starts[j + 1]
        B[j] = wJ[lo:hi].T @ J[lo:hi]
        grad[j] = r[lo:hi] @ wJ[lo:hi]
    return B, grad


def _assemble(
    bank: SurfaceBank,
    state: PatchState,
    a_seg: IntArray,
    b_seg: IntArray,
    Baa: FloatArray,
    ga: FloatArray,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """Triplets of ``A``, ``g`` and the diagonal blocks from every run's source block.

    Within one directed pair the destination's Jacobian is a fixed linear map of the source's,
    ``Jb = -T Ja`` (rotations about z): its spin arm is the source's plus ``Δ = s_a - s_b``,
    and its plane arm ``(x', y') = M (x_a, y_a) + c`` with ``M = [R_b' R_a]_xy`` and
    ``c = [R_b' Δ]_xy``.
    """
    n = len(bank.centre)
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
    Tt = np.swapaxes(T, 1, 2)
    Bbb = T @ Baa @ Tt
    Bab = -(Baa @ Tt)
    g = np.zeros((n, 6))
    diag = np.zeros((n, 6, 6))
    np.add.at(g, a_seg, -ga)
    np.add.at(g, b_seg, np.einsum("kij,kj->ki", T, ga))
    np.add.at(diag, a_seg, Baa)
    np.add.at(diag, b_seg, Bbb)
    ii, jj = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")

    def triplets(
        ra: IntArray, cb: IntArray, blk: FloatArray
    ) -> tuple[IntArray, IntArray, FloatArray]:
        return (
            (ra[:, None, None] * 6 + ii).ravel(),
            (cb[:, None, None] * 6 + jj).ravel(),
            blk.ravel(),
        )

    parts = [
        triplets(a_seg, a_seg, Baa),
        triplets(b_seg, b_seg, Bbb),
        triplets(a_seg, b_seg, Bab),
        triplets(b_seg, a_seg, np.swapaxes(Bab, 1, 2)),
    ]
    return (
        np.concatenate([x[0] for x in parts]),
        np.concatenate([x[1] for x in parts]),
        np.concatenate([x[2] for x in parts]),
        g,
        diag,
    )
