"""How wide the patches' slopes are smoothed for the Jacobian: chosen by their overlaps.

Every patch's candidate slopes (:func:`merge.refine.source_slopes.gaussian_slopes`, one per
width of :data:`WIDTHS`) and its plain ones (central differences averaged over three lines,
:meth:`merge.refine.bank.SurfaceBank.point_slopes`, standing for no smoothing) are compared, at
its points over its neighbours, with the neighbours' slopes there a node either side (the
derivative the residual's look-up has). Steps that solve ``Σ J r = 0`` with estimated slopes in
``J`` give a shift the variance ``σ² Σ J² / (Σ J J_true)²`` per axis; the neighbour's slope is
a noisy copy of ``J_true`` whose noise is independent of the source's, so ``Σ J J_ref``
estimates the denominator with no model of the noise or the surface: bias and noise are ranked
together, and a shrunk estimate's scale cancels. Only flat rows are compared (those the slopes
may replace, :data:`merge.refine.source_slopes.FLAT`).

One width serves the mosaic: the one the median patch gains most by, if it gains at all. How
fine the pixels are against the texture, and how strong the noise, are the instrument's
settings, not a patch's; chosen patch by patch, the paper grid's gratings took smoothing on a
few flat-faced patches whose comparison was a toss-up, and one draw's XY went 1.23 -> 1.53 nm.
Median gains measured (3 draws): 1 µm gratings 1.9, tgx1-1um 1.25, MoS2 1.6, the real 1-D
grating 1.007 (chosen); the paper grid's TGX1, flat face and folded surface 0.82-0.92 (none).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.parallel import each
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState, feet
from merge.refine.runs import Runs
from merge.refine.source_slopes import (
    FLAT,
    SLOPE_DTYPE,
    SourceSlopes,
    gaussian_slope_noise,
    gaussian_slopes,
    slopes_in_destination,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Candidate widths (Gaussian standard deviations, pixels). The 1 µm gratings' overlaps choose
#: 1.5 px mostly; the paper grid's none.
WIDTHS = (1.0, 1.5, 2.0, 3.0)
#: Compared rows a patch needs before its overlaps can choose for it.
LEAST_ROWS = 50
#: Patches whose overlaps are compared, at most (evenly spread over a larger mosaic). The
#: median gain of 32 is that of 64 within 0.04 on every bench case and at 400 patches (none
#: near the choice's 1; the paper grid's 50 patches 0.07 s sooner, 400 patches 0.11 s).
SAMPLE_PATCHES = 32
#: Patches per task shared among the cores.
PATCHES_PER_TASK = 8


def choose_source_slopes(
    bank: SurfaceBank,
    runs: Runs,
    state: PatchState,
    *,
    widths: Sequence[float] = WIDTHS,
) -> SourceSlopes | None:
    """The mosaic's smoothed slopes if its overlaps choose a width (module notes), else None.

    ``bank`` holds the raw heights (two nodes per pixel, every pixel a point) with no source
    slopes of its own in use (its look-ups are the reference); ``runs`` its rows at ``state``.
    """
    if bank.nodes < 2 or bank.stride != 1:
        raise ValueError("source slopes are chosen on the raw heights (stride 1, spline nodes)")
    if bank.source_slopes is not None:
        raise ValueError("the bank's look-ups must be its own while its slopes are chosen")
    n = len(bank.centre)
    # every source's runs, one after another (:class:`Runs`)
    bounds = np.searchsorted(runs.src, np.arange(n + 1))
    # the patches compared: all of a small mosaic, an even spread of a large one's (the choice
    # is the mosaic's; all 400 of a 400-patch mosaic took 55 % of its refinement's time)
    sample = np.unique(np.linspace(0, n - 1, min(n, SAMPLE_PATCHES)).round().astype(np.intp))
    # per patch compared: the variance its slopes give a shift, plain then each width; and
    # each width's mean square difference to the look-ups
    variance = np.full((len(sample), len(widths) + 1), np.nan)
    spread2 = np.full((len(sample), len(widths)), np.nan)

    def compare(k: int) -> None:
        c = int(sample[k])
        if bounds[c] == bounds[c + 1]:
            return
        own = runs.part(int(bounds[c]), int(bounds[c + 1]))
        found = _compare_one(bank, own, state, c, widths)
        if found is not None:
            variance[k], spread2[k] = found

    each(compare, range(len(sample)))
    seen = np.isfinite(variance).all(axis=1)
    if not seen.any():
        return None
    # one width for the mosaic, the one the median patch gains most by (a mean would follow
    # the patches whose overlaps are all flat), if it gains at all
    gain = np.median(variance[seen, :1] / variance[seen, 1:], axis=0)
    j = int(np.argmax(gain))
    if gain[j] <= 1.0:
        return None
    width = float(widths[j])
    grids: dict[int, NDArray[np.float16]] = {}

    def smooth(patches: range) -> None:
        for c in patches:
            slopes = gaussian_slopes(_pixels(bank, c), width, _pitch(bank, c))
            grids[c] = slopes.astype(SLOPE_DTYPE)

    each(smooth, [range(c, min(c + PATCHES_PER_TASK, n)) for c in range(0, n, PATCHES_PER_TASK)])
    ratio = gaussian_slope_noise(width) / bank.slope_noise
    return SourceSlopes(grids, float(np.median(spread2[seen, j])), ratio, width)


def _pixels(bank: SurfaceBank, c: int) -> FloatArray:
    """Patch ``c``'s heights at its pixels (the spline's nodes on them), float64."""
    m = bank.nodes
    out: FloatArray = bank.grid(c)[m:-m:m, m:-m:m].astype(np.float64)
    return out


def _pitch(bank: SurfaceBank, c: int) -> tuple[float, float]:
    return float(bank.dx[c]), float(bank.dy[c])


def _compare_one(
    bank: SurfaceBank, own: Runs, state: PatchState, c: int, widths: Sequence[float]
) -> tuple[FloatArray, FloatArray] | None:
    """Patch ``c``'s comparison over its runs ``own`` as source: the variance of a shift that
    its plain slopes and each width's give (len(widths) + 1,), and each width's mean square
    difference to the Jacobian's look-ups (len(widths),); None if too few rows compare."""
    rows = bank.rows(own)
    M, foot, solid = feet(bank, rows, state)
    run = np.repeat(np.arange(len(own)), np.diff(own.starts))
    # the reference: the destination's slopes a node either side, the derivative the
    # residual's look-up has; the Jacobian's, a pixel either side, is smoother, and on
    # roughness at the pixel scale lacks what smoothing takes too
    sharp = _slopes_at(bank, state, rows.dst, foot, solid, 1)
    looked_up = _slopes_at(bank, state, rows.dst, foot, solid, bank.nodes)
    heights, pitch = _pixels(bank, c), _pitch(bank, c)
    seen = [
        slopes_in_destination(gaussian_slopes(heights, w, pitch)[rows.row, rows.col], M[run])
        for w in widths
    ]
    # the widest's slope says where the surface is flat, the same rows for every candidate;
    # rows where any candidate is undefined (border, holes) are not compared
    with np.errstate(invalid="ignore"):
        use = np.isfinite(sharp).all(axis=1) & (np.sum(seen[-1] ** 2, axis=1) < FLAT**2)
    for s in seen:
        use &= np.isfinite(s).all(axis=1)
    where = np.flatnonzero(use)
    plain = slopes_in_destination(bank.point_slopes(rows, where), M[run[where]])
    known = np.isfinite(plain).all(axis=1)
    where, plain = where[known], plain[known]
    if len(where) < LEAST_ROWS:
        return None
    ref = sharp[where]
    variance = [_shift_variance(plain, ref)] + [_shift_variance(s[where], ref) for s in seen]
    spread2 = [float(np.mean(np.sum((s[where] - looked_up[where]) ** 2, axis=1))) for s in seen]
    return np.array(variance), np.array(spread2)


def _slopes_at(
    bank: SurfaceBank,
    state: PatchState,
    dst: IntArray,
    feet: FloatArray,
    solid: NDArray[np.bool_],
    reach: int,
) -> FloatArray:
    """(m, 2) the destinations' slopes (drift planes included) at ``feet`` (m, 3), differences
    ``reach`` nodes either side; NaN where not valid."""
    _, gx, gy, ok = bank.lookup(dst, feet, reach=reach)
    out = np.column_stack([gx, gy]) + state.slope[dst]
    out[~(ok & solid)] = np.nan
    return out


def _shift_variance(estimate: FloatArray, reference: FloatArray) -> float:
    """The variance (up to a common factor) of a shift that slopes ``estimate`` (m, 2) give,
    against the true slopes whose noisy copy is ``reference`` (m, 2; its noise independent of
    the estimate's).

    Steps that solve ``Σ J r = 0`` with a Jacobian ``J`` of estimated slopes have the variance
    ``σ² Σ J² / (Σ J J_true)²`` per axis: an estimate's noise inflates the numerator, its bias
    shrinks the denominator, and its scale cancels. The reference's noise averages out of
    ``Σ J J_ref``. Summed over both axes: the weaker one counts most, as in an XY error."""
    cross = np.einsum("ma,ma->a", estimate, reference)
    power = np.einsum("ma,ma->a", estimate, estimate)
    return float(np.sum(power / np.maximum(cross**2, 1e-300)))
