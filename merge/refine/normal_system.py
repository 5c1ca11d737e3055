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

Rows come in runs, one per directed pair (source, destination), stored as rectangles of the
source's points (:mod:`merge.refine.runs`). They are made and processed in blocks of whole
runs, so the temporaries stay a few megabytes however large the mosaic (large temporaries cost
page faults on every allocation, which dominated the time of 400-patch mosaics), and the blocks
are shared among the cores (:mod:`merge.core.parallel`). Three passes: every row's residual and
slopes (kept, 8 bytes a row) with the robust scale, which needs all of them; the scan lines'
sums, for the size of their offsets; the information of every run.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.core.information import line_design, line_sums, noise_share, psd_part
from merge.core.parallel import each
from merge.core.progress import checkpoint
from merge.refine.assembly import assemble
from merge.refine.bank import SurfaceBank
from merge.refine.lines import (
    OffsetRatios,
    SharedLines,
    group_sums,
    marginalise_offsets,
    shared_ratios,
)
from merge.refine.rows import PatchState, jacobians, lever_arms, residuals, segment_sums
from merge.refine.runs import BLOCK_ROWS, BlockPlan, Runs, block_plan

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: Float arrays of any width (float32 where the mosaic's memory counts).
Floats = NDArray[np.floating[Any]]

#: Storage of every row's residual and of its destination's slopes between the build's passes
#: (:class:`ScoredRows`): all that a row holds beyond its block.
RESIDUAL_DTYPE = np.float32
GRAD_DTYPE = np.float16
#: Storage of the robust weights a level keeps from one step to the next (in [0, 1]: a
#: thousandth is more than their own precision).
WEIGHT_DTYPE = np.float16
#: Rows the robust scale is the median of, at most (evenly spread over the mosaic; a median of
#: millions moves by a thousandth of itself, and a copy of every row's residual was a sixth of
#: the build's memory).
MEDIAN_ROWS = 1 << 22


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
    (:func:`merge.core.information.line_design`); ``slope_count`` (then too, n) the residuals
    that involve a patch counted by their slopes' noise, a look-up's as one (fewer than
    ``count`` where the sources' smoothed slopes stand in, :mod:`merge.refine.source_slopes`).
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
    slope_count: FloatArray | None = None
    #: (m,) the robust weight of every row of the build, if asked for (``keep_weights``)
    weights: Floats | None = None

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


def build_normal_system(
    bank: SurfaceBank,
    runs: Runs,
    state: PatchState,
    noise: float,
    *,
    block_rows: int | None = None,
    signal: bool = False,
    lines: bool = True,
    weights: Floats | None = None,
    keep_weights: bool = False,
) -> NormalSystem:
    """The Gauss-Newton system over all correspondences, and per-patch statistics.

    Parameters
    ----------
    bank : SurfaceBank
        The patches of this level.
    runs : Runs
        The rows, run by run (:meth:`SurfaceBank.candidates`).
    state : PatchState
        Current placement of every patch.
    noise : float
        Height noise, pixel units: the least robust scale.
    block_rows : int, keyword-only
        Rows per block; changes memory and speed, never the result. Default
        :func:`block_plan`'s (which also shares the blocks among the cores or not).
    signal : bool, keyword-only
        Also compute ``signal_vals`` (for uncertainties, not for steps).
    lines : bool, keyword-only
        Marginalise the offsets of scan lines (:mod:`merge.refine.lines`), their size measured on
        the residuals.
    weights : (m,) array, keyword-only
        Robust weights of the rows of ``runs``, in order, instead of their own Cauchy weights.
    keep_weights : bool, keyword-only
        Return the robust weights this build used (``NormalSystem.weights``).
    """
    if weights is not None and len(weights) != runs.size:
        raise ValueError(f"weights must hold one per row ({runs.size}), not {len(weights)}")
    n = len(bank.centre)
    plan = block_plan(int(np.dot(bank.nx, bank.ny)))
    if block_rows is not None:
        plan = BlockPlan(block_rows, plan.on_cores)
    blocks = runs.blocks(plan.rows)
    rows = None if runs.size == 0 else _scored_rows(bank, runs, state, noise, blocks, plan.on_cores)
    if rows is None:
        return NormalSystem.empty(n)
    if weights is not None:
        rows = replace(rows, fixed=weights)
    kept = None
    if keep_weights:  # the weights this build uses, for later builds to hold
        kept = rows.fixed if rows.fixed is not None else rows.weights()
    rms, rscale = rows.rms, rows.rscale
    noise2 = None
    if signal:
        pitch2 = 0.5 * (bank.dx[runs.dst] ** -2 + bank.dy[runs.dst] ** -2)
        noise2 = bank.slope_noise * noise**2 * pitch2
    rho = (
        _offset_ratios(runs, rows, blocks, plan.on_cores) if lines else OffsetRatios(np.inf, np.inf)
    )
    checkpoint()  # between the passes too: the lines' ratios took up to a second on 10,000 patches
    info = _run_information(bank, runs, state, rows, blocks, rho, noise2, on_cores=plan.on_cores)
    del rows  # every row's residual and slopes: not needed past here
    signal_blocks, design = None, 1.0
    if info.share is not None:
        signal_blocks = psd_part(info.Baa - info.share)
        # the design effect of the raw Z scores, on top of the offsets' model: measured on the
        # whitened scores (what the model leaves correlated) the Z sigmas were 1.3-1.9 x too
        # small on TGX1, its flat face and the grating (a bowl no line model holds); this way
        # they are 0.9-1.4 x, and cautious (0.3-0.6 x) on MoS2 and the folded surface
        design = line_design(info.line_sums)
        checkpoint()
    # the report's per-patch sums, over every row of the mosaic: not for steps
    count, sq, slope_count = np.zeros(n), np.zeros(n), np.zeros(n)
    if signal:
        for ends in (runs.src, runs.dst):  # a row involves both patches of its pair
            count += np.bincount(ends, weights=info.patch_sums[:, 0], minlength=n)
            sq += np.bincount(ends, weights=info.patch_sums[:, 1], minlength=n)
            slope_count += np.bincount(ends, weights=info.patch_sums[:, 2], minlength=n)
    a_seg, b_seg = runs.src, runs.dst
    a_rows, a_cols, vals, g, diag = assemble(
        bank, state, a_seg, b_seg, info.Baa, info.ga, info.shared
    )
    signal_vals = None
    if signal_blocks is not None:
        checkpoint()
        signal_vals = assemble(bank, state, a_seg, b_seg, signal_blocks, info.ga, info.shared)[2]
    return NormalSystem(
        rows=a_rows,
        cols=a_cols,
        vals=vals,
        g=g,
        diag=diag,
        count=count,
        sq=sq,
        rms=rms,
        rscale=rscale,
        signal_vals=signal_vals,
        line_design=design,
        slope_count=slope_count if signal else None,
        weights=kept,
    )


@dataclass(frozen=True)
class ScoredRows:
    """Pass 1 of the build: per row (m,) its residual ``r`` (NaN where its foot misses its
    destination) and the destination's slopes ``grad`` (m, 2); the valid residuals' RMS ``rms``
    and robust scale ``rscale``. What a row holds between the passes, for every row of the
    mosaic at once: 8 bytes (float32 residuals, a ten-millionth of their size; float16 slopes,
    which only tilt a Jacobian), and one more where some patches' slopes are their own smoothed
    ones: ``smoothed`` (m,) whether a row's are (their noise is not a look-up's)."""

    r: Floats
    grad: Floats
    rms: float
    rscale: float
    smoothed: NDArray[np.bool_] | None = None
    #: (m,) robust weights kept from an earlier step (:func:`build_normal_system`'s
    #: ``weights``), or None: each row's own Cauchy weight
    fixed: Floats | None = None

    def block(self, lo: int, hi: int) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
        """Rows ``[lo, hi)``: residual (0 where not valid), validity and robust weight."""
        r = self.r[lo:hi].astype(np.float64)
        ok = np.isfinite(r)
        r[~ok] = 0.0
        if self.fixed is not None:
            return r, ok, np.where(ok, self.fixed[lo:hi].astype(np.float64), 0.0)
        return r, ok, np.where(ok, cauchy(r, self.rscale), 0.0)

    def weights(self) -> Floats:
        """(m,) every row's Cauchy weight here (0 where not valid), block by block."""
        out = np.empty(len(self.r), dtype=WEIGHT_DTYPE)
        for lo in range(0, len(self.r), BLOCK_ROWS):
            checkpoint()  # 50 million rows (10,000 patches) take 0.3 s
            r = self.r[lo : lo + BLOCK_ROWS].astype(np.float64)
            out[lo : lo + BLOCK_ROWS] = np.nan_to_num(cauchy(r, self.rscale))
        return out


def cauchy(r: FloatArray, rscale: float) -> FloatArray:
    """The Cauchy weight of residuals ``r`` at robust scale ``rscale`` (both pixel units)."""
    out: FloatArray = 1.0 / (1.0 + (r / (3.0 * rscale)) ** 2)
    return out


def _scored_rows(
    bank: SurfaceBank,
    runs: Runs,
    state: PatchState,
    noise: float,
    blocks: list[tuple[int, int]],
    on_cores: bool,
) -> ScoredRows | None:
    """Pass 1: every row's residual and slopes (block by block, on the cores if
    ``on_cores``), then the robust scale, which needs all of them; None if no row is valid."""
    m = runs.size
    r = np.empty(m, dtype=RESIDUAL_DTYPE)
    grad = np.empty((m, 2), dtype=GRAD_DTYPE)
    smoothed = None if bank.source_slopes is None else np.empty(m, dtype=bool)
    squares = np.zeros((len(blocks), 2))  # per block: valid rows, their sum of squares

    def block_residuals(j: int) -> None:
        lo, hi = runs.starts[blocks[j][0]], runs.starts[blocks[j][1]]
        rr, ok, gg, own = residuals(bank, bank.rows(runs, *blocks[j]), state)
        r[lo:hi] = np.where(ok, rr, np.nan)
        grad[lo:hi] = gg
        if smoothed is not None:
            smoothed[lo:hi] = own
        squares[j] = ok.sum(), rr @ rr

    each(block_residuals, range(len(blocks)), on_cores=on_cores)
    valid, total = squares.sum(axis=0)
    if valid == 0:
        return None
    rms = float(np.sqrt(total / valid))
    sample = r[:: max(1, m // MEDIAN_ROWS)]
    used = sample[np.isfinite(sample)]
    np.abs(used, out=used)
    rscale = max(1.4826 * float(np.median(used, overwrite_input=True)), noise)
    return ScoredRows(r, grad, rms, rscale, smoothed)


def _offset_ratios(
    runs: Runs, rows: ScoredRows, blocks: list[tuple[int, int]], on_cores: bool
) -> OffsetRatios:
    """:func:`merge.refine.lines.shared_ratios` over every line of every run, block by block."""
    lines = runs.box[:, 1] - runs.box[:, 0]
    first_group = np.concatenate([[0], np.cumsum(lines)])
    sums = np.empty((4, int(first_group[-1])))

    def block_sums(block: tuple[int, int]) -> None:
        lo, hi = runs.starts[block[0]], runs.starts[block[1]]
        r, ok, w = rows.block(lo, hi)
        g_lo, g_hi = first_group[block[0]], first_group[block[1]]
        sums[:, g_lo:g_hi] = group_sums(r, w, ok, runs.groups(*block))

    each(block_sums, blocks, on_cores=on_cores)
    spans = np.repeat(runs.box[:, 2:], lines, axis=0)
    return shared_ratios(sums, runs.lines(), spans)


@dataclass(frozen=True)
class RunInformation:
    """Pass 2 of the build, per run (k runs): the source's information block ``Baa`` (k, 6, 6)
    and gradient ``ga`` (k, 6), the noise's ``share`` of each block (or None); per run the
    valid rows, their squared distances along the surface normal and their slopes' noise in
    look-ups' worth ``patch_sums`` (k, 3), and
    the mosaic's :func:`merge.core.information.line_sums` (2,); what the scan lines' shared
    offsets take out between runs of one source (``shared``)."""

    Baa: FloatArray
    ga: FloatArray
    share: FloatArray | None
    patch_sums: FloatArray
    line_sums: FloatArray
    shared: SharedLines


def _run_information(
    bank: SurfaceBank,
    runs: Runs,
    state: PatchState,
    rows: ScoredRows,
    blocks: list[tuple[int, int]],
    rho: OffsetRatios,
    noise2: FloatArray | None = None,
    *,
    on_cores: bool = True,
) -> RunInformation:
    """Pass 2: per run, the source's information block and gradient, the offsets of its lines
    marginalised (``rho`` from :func:`merge.refine.lines.shared_ratios`; a block holds every
    run of its sources, :meth:`Runs.blocks`, so every line's groups); with ``noise2`` (k,)
    (the variance of a looked-up slope of the noise per run) also the share of each block that
    noise claims (:func:`merge.core.information.noise_share`) and the report's sums."""
    k = len(runs)
    Baa, ga = np.empty((k, 6, 6)), np.empty((k, 6))
    share = None if noise2 is None else np.empty((k, 6, 6))
    patch_sums = np.zeros((k, 3))
    lines = np.zeros((len(blocks), 2))
    shared = [SharedLines.none()] * len(blocks)

    def information(j: int) -> None:
        first, last = blocks[j]
        lo, hi = runs.starts[first], runs.starts[last]
        block = bank.rows(runs, first, last)
        r, ok, w = rows.block(lo, hi)
        grad = rows.grad[lo:hi].astype(np.float64)
        points = bank.point_xyz(block)
        np.nan_to_num(points, copy=False)  # holes: their rows are not valid
        arm = lever_arms(points, block, state)
        J = jacobians(bank, block, state, grad, ok, arm, points)
        Baa[first:last], ga[first:last] = segment_sums(J, w, r, block.starts)
        if share is not None and noise2 is not None:
            # a row's slope noise against a look-up's: less where the source's smoothed slopes
            # stand in for it
            ratio = np.ones(hi - lo)
            if rows.smoothed is not None and bank.source_slopes is not None:
                own = rows.smoothed[lo:hi]
                ratio[own] = bank.source_slopes.noise_ratio
            share[first:last] = noise_share(
                w * ratio, arm, block.starts, bank.radius[runs.src[first:last]], noise2[first:last]
            )
            lines[j] = line_sums(w * r, block.groups)
            d2 = r**2 / (1.0 + np.einsum("ij,ij->i", grad, grad))
            patch_sums[first:last, 0] = np.add.reduceat(ok, block.starts[:-1], dtype=np.float64)
            patch_sums[first:last, 1] = np.add.reduceat(d2, block.starts[:-1])
            patch_sums[first:last, 2] = np.add.reduceat(ok * ratio, block.starts[:-1])
        between = marginalise_offsets(
            J,
            w,
            r,
            block.starts,
            block.groups,
            rho,
            Baa[first:last],
            ga[first:last],
            runs.lines(first, last),
        )
        shared[j] = between.moved(first)

    each(information, range(len(blocks)), on_cores=on_cores)
    line_total = lines.sum(axis=0)
    return RunInformation(Baa, ga, share, patch_sums, line_total, SharedLines.joined(shared))
