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
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.core.information import line_design, noise_share, psd_part
from merge.core.parallel import each
from merge.refine.bank import SurfaceBank
from merge.refine.lines import line_groups, marginalise_offsets, offset_ratio
from merge.refine.rows import PatchState, jacobians, lever_arms, residuals, segment_sums

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: Float arrays of any width (float32 where the mosaic's memory counts).
Floats = NDArray[np.floating[Any]]
#: Integer arrays of any width.
Ints = NDArray[np.integer[Any]]
Candidates = tuple[Ints, Ints, Ints, IntArray]

#: Rows per block of the system build (whole runs are kept together).
BLOCK_ROWS = 1 << 15


@dataclass(frozen=True)
class NormalSystem:
    """The sparse system ``A x = g`` (6 unknowns per patch) and fit statistics.

    ``rows``, ``cols``, ``vals`` are the triplets of ``A``; ``g`` (n, 6); per patch ``count`` (n,)
    residuals that involve it and ``sq`` (n,) the sum of their squares as distances along the
    surface normal (with ``signal_vals`` only; zeros without), and ``diag`` (n, 6, 6) its own
    information block; ``rms`` and ``rscale`` (robust scale)
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

    @classmethod
    def empty(cls, n: int) -> NormalSystem:
        """The system of ``n`` patches without a single correspondence."""
        none = np.empty(0, dtype=np.intp)
        return cls(
            none,
            none,
            np.empty(0),
            np.zeros((n, 6)),
            np.zeros(n),
            np.zeros(n),
            np.zeros((n, 6, 6)),
            0.0,
        )


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
    blocks = _blocks(starts, block_rows)
    rows = None if len(idx) == 0 else _scored_rows(bank, cand, state, noise, blocks)
    if rows is None:
        return NormalSystem.empty(n)
    # the residuals of one source line share its offset (merge.refine.lines); no groups, none
    line = bank.line[idx]
    groups = line_groups(starts, line) if lines else np.empty(0, dtype=np.intp)
    a_seg, b_seg = src[starts[:-1]].astype(np.intp), dst[starts[:-1]].astype(np.intp)
    noise2 = None
    if signal:
        pitch2 = 0.5 * (bank.dx[b_seg] ** -2 + bank.dy[b_seg] ** -2)
        noise2 = bank.slope_noise * noise**2 * pitch2
    Baa, ga, share = _run_information(bank, cand, state, rows, groups, blocks, noise2)
    signal_blocks, design = None, 1.0
    if share is not None:
        signal_blocks = psd_part(Baa - share)
        # the design effect of the raw Z scores, on top of the offsets' model: measured on the
        # whitened scores (what the model leaves correlated) the Z sigmas were 1.3-1.9 x too
        # small on TGX1, its flat face and the grating (a bowl no line model holds); this way
        # they are 0.9-1.4 x, and cautious (0.3-0.6 x) on MoS2 and the folded surface
        design = line_design(rows.w * rows.r, starts, line)
    # the report's per-patch sums, over every row of the mosaic: not for steps
    count, sq = _patch_sums(n, src, dst, rows) if signal else (np.zeros(n), np.zeros(n))
    a_rows, a_cols, vals, g, diag = _assemble(bank, state, a_seg, b_seg, Baa, ga)
    signal_vals = None
    if signal_blocks is not None:
        signal_vals = _assemble(bank, state, a_seg, b_seg, signal_blocks, ga)[2]
    return NormalSystem(
        rows=a_rows,
        cols=a_cols,
        vals=vals,
        g=g,
        diag=diag,
        count=count,
        sq=sq,
        rms=rows.rms,
        rscale=rows.rscale,
        signal_vals=signal_vals,
        line_design=design,
    )


@dataclass(frozen=True)
class ScoredRows:
    """Pass 1 of the build: per row (m,) its residual ``r``, whether its foot lies on its
    destination (``ok``), its robust weight ``w`` and the destination's slopes ``grad`` (m, 2);
    the valid residuals' RMS ``rms`` and robust scale ``rscale``. Kept for every row of the
    mosaic at once, so weights and slopes are float32 (a ten-millionth of what they weigh and
    tilt), and no more than these (a row held 64 bytes, now 21)."""

    r: FloatArray
    ok: NDArray[np.bool_]
    grad: Floats
    w: Floats
    rms: float
    rscale: float


def _scored_rows(
    bank: SurfaceBank,
    cand: Candidates,
    state: PatchState,
    noise: float,
    blocks: list[tuple[int, int]],
) -> ScoredRows | None:
    """Pass 1: every row's residual and slopes (block by block, on the cores), then the robust
    scale and the Cauchy weights, which need all of them; None if no row is valid."""
    _, dst, idx, starts = cand
    m = len(idx)
    r, ok = np.empty(m), np.empty(m, dtype=bool)
    grad = np.empty((m, 2), dtype=np.float32)

    def block_residuals(block: tuple[int, int]) -> None:
        lo, hi = starts[block[0]], starts[block[1]]
        r[lo:hi], ok[lo:hi], grad[lo:hi] = residuals(
            bank, idx[lo:hi], dst[lo:hi], starts[block[0] : block[1] + 1] - lo, state
        )

    each(block_residuals, blocks)
    used = np.abs(r[ok])
    if used.size == 0:
        return None
    rms = float(np.sqrt(np.mean(used**2)))
    rscale = max(1.4826 * float(np.median(used)), noise)
    del used
    w = np.where(ok, 1.0 / (1.0 + (r / (3.0 * rscale)) ** 2), 0.0).astype(np.float32)
    return ScoredRows(r, ok, grad, w, rms, rscale)


def _run_information(
    bank: SurfaceBank,
    cand: Candidates,
    state: PatchState,
    rows: ScoredRows,
    groups: IntArray,
    blocks: list[tuple[int, int]],
    noise2: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Pass 2: per run, the source's information block (k, 6, 6) and gradient (k, 6), the
    offsets of its lines (``groups``) marginalised; with ``noise2`` (k,) (the variance of a
    looked-up slope of the noise per run) also the share of each block that noise claims
    (:func:`merge.core.information.noise_share`)."""
    _, dst, idx, starts = cand
    r, w, ok = rows.r, rows.w, rows.ok
    rho = offset_ratio(r, w, ok, groups)
    k = len(starts) - 1
    Baa, ga = np.empty((k, 6, 6)), np.empty((k, 6))
    share = None if noise2 is None else np.empty((k, 6, 6))
    a_seg = cand[0][starts[:-1]]

    def information(block: tuple[int, int]) -> None:
        first, last = block
        lo, hi = starts[first], starts[last]
        runs = starts[first : last + 1] - lo
        arm = lever_arms(bank, idx[lo:hi], runs, state)
        J = jacobians(bank, idx[lo:hi], dst[lo:hi], runs, state, rows.grad[lo:hi], ok[lo:hi], arm)
        Baa[first:last], ga[first:last] = segment_sums(J, w[lo:hi], r[lo:hi], runs)
        if share is not None and noise2 is not None:
            share[first:last] = noise_share(
                w[lo:hi], arm, runs, bank.radius[a_seg[first:last]], noise2[first:last]
            )
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
    return Baa, ga, share


def _patch_sums(n: int, src: Ints, dst: Ints, rows: ScoredRows) -> tuple[FloatArray, FloatArray]:
    """Per patch (n,): the valid residuals that involve it, and the sum of their squares as
    distances along the surface normal (how far the surfaces lie apart: a flank misplaced by a
    nanometre is tens of nanometres off in height)."""
    ok = rows.ok
    count = np.bincount(src[ok], minlength=n) + np.bincount(dst[ok], minlength=n)
    d2 = rows.r**2 / (1.0 + np.einsum("ij,ij->i", rows.grad, rows.grad))
    sq = np.asarray(
        np.bincount(src, weights=d2, minlength=n) + np.bincount(dst, weights=d2, minlength=n),
        dtype=np.float64,
    )
    return count.astype(np.float64), sq


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
