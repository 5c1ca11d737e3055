"""One level of the refinement's schedule (:mod:`merge.refine.icp`): its Gauss-Newton steps
and when they stop.

A level iterates steps of every patch not held (:func:`run_level`): the system built at the
current placement (:mod:`merge.refine.normal_system`), its priors, the solve
(:mod:`merge.refine.solve`), the move and the gauge. It stops when the steps still to come
would move no height by :data:`HEIGHT_TOL` of the noise (the raw level, through
:mod:`merge.refine.convergence`) or no patch by the level's tolerance, when the cost stalls
(:data:`STALLS` steps in a row, or a cycle of up to :data:`CYCLE` steps), or when it runs out
of iterations; a level's second step extrapolates at the last level's rate of convergence where
that is known. Once the raw level's steps are small its robust weights are held
(:data:`FREEZE_MOTION`; sooner where only patches the start measured still move,
:data:`FREEZE_MEASURED`). :class:`Fit` is what the levels hand each other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from merge.core.errors import MergeCancelled
from merge.core.progress import checkpoint
from merge.refine.bank import SurfaceBank
from merge.refine.convergence import height_effect, remaining, slope_rms
from merge.refine.normal_system import Floats, NormalSystem, build_normal_system
from merge.refine.runs import Runs
from merge.refine.slope_widths import choose_source_slopes
from merge.refine.solve import Priors, solve_system
from merge.refine.state import MosaicState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Progress = Callable[[int, float], None]


@dataclass(frozen=True)
class Level:
    """One stage of the coarse-to-fine schedule: smoothing (pixels) and point stride."""

    smooth: float
    stride: int
    max_iter: int
    tol: float  # largest patch motion (pixels) that counts as converged
    #: pixels from both patches' borders within which the level takes no rows, where that
    #: leaves a pair half its rows (:meth:`merge.refine.bank.SurfaceBank.candidates`)
    band: float = 0.0


STALL = 1e-4
#: The raw level stops once a step changes no height by more than this fraction of the noise
#: (through the RMS slope for XY and spin): what is left would add a few thousandths of the
#: noise to the map error in quadrature, and a pixel-based tolerance alone is arbitrary in
#: physical units (1e-3 px is 20 pm at 20 nm pixels, 2 pm at 2 nm, where an iteration over
#: 9 patches of 512 x 512 costs a second). Bench draws, against none: iterations -19 % (the
#: variations -24 %), every map/floor within 0.01 or better (grid draws 5, 7: 1.17, 1.15 ->
#: 1.08, 1.10); at 0.2 the grating's XY starts to suffer (draw 3: 2.7 -> 4.5 nm). What the
#: steps still to come would move (:func:`merge.refine.convergence.remaining`) counts, not the
#: last step alone: where every step is a fifth of the one before, the step after one of 0.15
#: is not needed (50 TGX1 patches: 9 -> 8 iterations; 100 variations -4 %, map/floor within
#: 0.02 either way).
HEIGHT_TOL = 0.1
#: Iterations in a row the cost must stall for: along a grating's stripes the patches creep
#: (their few defects hold them loosely), and the cost may pause once on the way (grid draws
#: 0, 3, 5, 25, 30: map/floor 1.10, 1.50, 1.13, 1.18, 1.38 with one -> 1.04, 1.09, 1.14, 1.09,
#: 1.10 with two; TGX1 as before, one iteration more).
STALLS = 2
#: Longest cycle of steps that counts as a stall (:func:`_cycled`).
CYCLE = 3
#: The raw level holds its robust weights once a step moved no patch by more than this many
#: times the level's tolerance (0.01 px): past there the Cauchy weights of rows on steep ramps
#: settle more slowly than the patches, which follow them (the paper grid's chessboards with
#: 50 nm ramps, 2.5 px wide: steps of 0.003-0.01 px in one direction for 20 steps, the plain
#: RMS rising, until the iterations nearly ran out). Not before: a 2 x 2 mosaic of the real
#: grating slipped along its stripes creeps by 0.02-0.04 px a step, runs out of iterations and
#: is flagged; its weights held from the level's third step, it converged, its four patches
#: claimed held 186 nm off. :func:`merge.refine.normal_system.build_normal_system`'s
#: ``weights``.
FREEZE_MOTION = 10.0
#: The same for patches the start measured in XY along both axes: their correlation peaks
#: placed them, so what still moves them by 0.01-0.04 px a step is the weights of the rows on
#: steep ramps settling, not a slip (held below 0.01 px only, the paper grid's 50 nm ramps took
#: 29-37 iterations and 3.4-3.7 s for the CLI; held from here, at most 26 and 2.9 s over the
#: sweep's 240 runs, their map/floor within 2.6 % either way and XY RMS 0.84 -> 0.87 nm on the
#: slowest case, every other case and the bench identical). :data:`FREEZE_MOTION` stays the
#: limit wherever a patch the start did not measure still moves.
FREEZE_MEASURED = 40.0
#: A smoothed level's tolerance, as a multiple of its own, for patches the start measured in
#: XY along both axes. Such a level only brings patches into the raw level's reach, and the raw
#: level's optimum lies some tenths of a pixel from a smoothed one's anyway (the paper grid's
#: tip-drawn steps: its first step moved patches 0.6 px): the last steps of the one-pixel
#: level, polishing spins by 0.03-0.05 px, bought nothing there. Patches the start did not
#: measure keep the level's own tolerance (along a grating's stripes they creep, and stopped
#: short they stay off). Tip-drawn 0.6 µm steps at 20 nm, 6 draws: 14-27 -> 9-25 iterations,
#: XY the same within 0.08 nm; the grating sweeps (3 draws of each case) 693 -> 656 iterations
#: (tanh ramps) and 1035 -> 1010 (tip-drawn), every map/floor and XY/bound within 0.03; the
#: variations' medians the same within 0.02 nm (map/floor within 0.002). At 4 x, MoS2's XY
#: median went 1.02 -> 1.25 nm (its raw level stops where the smoothed one leaves it, within
#: its own tolerance).
MEASURED_TOL = 2.0
#: Standard deviation (radians) of the prior on a patch's rotation about z.
SPIN_PRIOR = np.radians(2.0)


@dataclass
class Fit:
    """What the refinement carries from level to level: the placement of every patch
    (``state``, pixel units of ``scale`` metres), where the start put it (``start_s``), the
    raw surfaces (``base``), the height noise (pixel units), and the iterations so far with the
    residual RMS (metres) of each; how far the last step moved every patch in the plane
    (``last_step`` (n,), pixels: XY and spin times the radius); how fast the last level's
    steps shrank (``ratio``: its last step's motion over the one before, infinite where it took
    fewer than three)."""

    state: MosaicState
    start_s: FloatArray
    base: SurfaceBank
    scale: float
    noise: float
    iteration: int = 0
    history: list[float] = field(default_factory=list)
    system: NormalSystem | None = None
    last_step: FloatArray | None = None
    ratio: float = np.inf


@dataclass(frozen=True)
class LevelSetup:
    """One level's surfaces and system: ``bank``; the pairs in it and the patches ``held``
    (None: none); the look-up ``margin`` (pixels); whether it works on the raw heights; the
    priors' sigmas of the drift planes (x, y) and of the XY shifts (pixel units); the patches
    the start ``measured`` in XY along both axes (None: not known, as if none); the level's
    border ``band`` (:attr:`Level.band`)."""

    bank: SurfaceBank
    pairs: IntArray
    held: NDArray[np.bool_] | None
    margin: float
    raw: bool
    plane_sigma: FloatArray
    shift_sigma: float = np.inf
    measured: NDArray[np.bool_] | None = None
    band: float = 0.0


def run_level(
    fit: Fit,
    lv: LevelSetup,
    level: Level,
    *,
    progress: Progress | None,
    cancel: Callable[[], bool] | None,
    keep: bool = False,
) -> bool:
    """Iterate one level until it converges (True) or runs out of iterations (False); with
    ``keep``, its steps' systems (but the first's) carry their signal share, and the last
    one's is kept in ``fit.system`` if that step settled the level
    (:func:`merge.refine.icp.refine`'s ``report``)."""
    state, bank = fit.state, lv.bank
    cand = bank.candidates(lv.pairs, state.R, state.s, lv.margin, band=lv.band)
    if lv.raw:
        # the Jacobians' slopes: the patches' own, smoothed, if the mosaic's overlaps at the
        # placement the smoothed levels reached show them better than the look-ups
        bank.source_slopes = None
        bank.source_slopes = choose_source_slopes(bank, cand, state)
    moved = 0.0
    previous = np.inf
    recent: list[tuple[float, FloatArray]] = []  # the last steps' cost and motion
    stalls = 0
    # on the raw heights, once the steps still to come move no height by HEIGHT_TOL of the
    # noise the level is done
    slope = slope_rms(bank) if lv.raw else np.inf
    effect = motion = np.inf
    motions: FloatArray | None = None  # how far the last step moved every patch (pixels)
    weights = None  # the robust weights held (FREEZE_MOTION)
    carried, fit.ratio = fit.ratio, np.inf  # how fast the last level's steps shrank
    for step in range(level.max_iter):
        if cancel is not None and cancel():
            raise MergeCancelled("merge cancelled")
        checkpoint()
        if moved > 0.5 * lv.margin:
            cand = bank.candidates(lv.pairs, state.R, state.s, lv.margin, band=lv.band)
            moved = 0.0
            weights = None
        fit.system = None  # a step's system is dropped before the next one is built
        # the level's first step is never the last but where no patch moves: its system goes
        # without the signal share, which costs a tenth of a build
        signal = keep and step > 0
        freeze = weights is None and lv.raw and _small(motions, lv.measured, level.tol)
        rms, delta, stats = _step(fit, lv, cand, signal=signal, weights=weights, freeze=freeze)
        if freeze:
            weights = stats.weights
        fit.system = stats if signal else None
        del stats
        # the level's first step moves from the last level's optimum to this one's (smoothing
        # and stride change it): its length says nothing of how fast this level converges,
        # but the last level's ratio (``carried``) does, where it had one; the second step's
        # ratio to the first is then taken as no smaller (400 folded patches: the raw level's
        # steps 0.56, 0.039, 0.0064 px; the one-pixel level's last ratio, 0.12, says the
        # third, 0.6 s of 5, was not needed)
        trusted = step > 1 or (step == 1 and np.isfinite(carried))
        at_least = carried if step == 1 else 0.0
        before = motions
        motions = np.abs(delta[:, :3]).max(axis=1) + np.abs(delta[:, 3:]).max(axis=1)
        # the looser tolerance from the third step on: a level that ends sooner leaves the
        # next none of its rate of convergence (the raw level of 5 x 5 folded patches then
        # took a third step, dearer than the smoothed one it saved); both steps measured alike
        scale = _tolerance_scale(lv) if step >= 2 else 1.0
        motion = float((motions / scale).max(initial=0))
        last_motion = (
            float((before / scale).max(initial=0)) if trusted and before is not None else np.inf
        )
        moved += float(motions.max(initial=0))
        fit.last_step = np.hypot(delta[:, 0], delta[:, 1]) + np.abs(delta[:, 3])
        fit.iteration += 1
        fit.history.append(rms * fit.scale)
        if progress is not None:
            progress(fit.iteration, rms * fit.scale)
        checkpoint(1)
        # converged when no patch moves, or when the cost no longer falls (the motion left is
        # then in directions the data do not constrain, e.g. XY over a flat overlap)
        # or when the steps came back to where they were two or three steps before, the cost
        # too: a cycle (overlaps a few pixels wide, border columns gained and lost in turn),
        # not the creep along a grating's stripes, whose steps go on the same way
        recent = (recent + [(rms, delta)])[-(CYCLE + 1) :]
        stalls = stalls + 1 if abs(previous - rms) <= STALL * rms or _cycled(recent) else 0
        previous = rms
        last_effect = effect if trusted else np.inf
        effect = height_effect(delta, slope)
        settled = remaining(effect, last_effect, at_least=at_least) < HEIGHT_TOL * fit.noise
        # the motion still to come, as the heights' (a level of 3,600 patches, smoothed: steps
        # of 0.69, 0.087 and 0.023 px, where the second's tail was 0.012 px, within the 0.05
        # of the level's tolerance; the largest motion of many patches grows with their number)
        if remaining(motion, last_motion, at_least=at_least) < level.tol or settled:
            fit.ratio = motion / last_motion if step > 1 and last_motion > 0 else np.inf
            return True  # the report's system (if kept) is this step's
        if stalls >= STALLS:
            fit.system = None  # the last step may have moved patches along a flat overlap
            return True
    fit.system = None
    return False


def _tolerance_scale(lv: LevelSetup) -> FloatArray | float:
    """Per patch, the multiple of the level's tolerance its motion is held to: on a smoothed
    level :data:`MEASURED_TOL` for the patches the start measured (``lv.measured``), else 1."""
    if lv.raw or lv.measured is None:
        return 1.0
    return np.where(lv.measured, MEASURED_TOL, 1.0)


def _small(motions: FloatArray | None, measured: NDArray[np.bool_] | None, tol: float) -> bool:
    """Whether the last step's ``motions`` (n,) are small enough to hold the robust weights:
    no patch moved by :data:`FREEZE_MOTION` x ``tol``, or by :data:`FREEZE_MEASURED` x ``tol``
    where the start ``measured`` it along both axes (None: none)."""
    if motions is None:
        return False
    limit = np.full(len(motions), FREEZE_MOTION * tol)
    if measured is not None:
        limit[measured] = FREEZE_MEASURED * tol
    return bool(np.all(motions < limit))


def _cycled(recent: list[tuple[float, FloatArray]]) -> bool:
    """Whether the last steps of ``recent`` (cost, motion (n, 6)) closed a cycle: for a cycle
    of two or three (up to :data:`CYCLE`), the cost back within :data:`STALL` of where it was
    and the motions of the steps since summing to a tenth of their lengths at most."""
    rms = recent[-1][0]
    for k in range(2, min(CYCLE, len(recent) - 1) + 1):
        steps = [d.ravel() for _, d in recent[-k:]]
        length = sum(float(np.linalg.norm(d)) for d in steps)
        back = abs(recent[-k - 1][0] - rms) <= STALL * rms
        if back and length > 0 and float(np.linalg.norm(np.sum(steps, axis=0))) <= 0.1 * length:
            return True
    return False


def _step(
    fit: Fit,
    lv: LevelSetup,
    cand: Runs,
    *,
    signal: bool = False,
    weights: Floats | None = None,
    freeze: bool = False,
) -> tuple[float, FloatArray, NormalSystem]:
    """One Gauss-Newton step of every patch not held: the system at the current placement, its
    priors, the solve, the move and the gauge; the residual RMS (pixel units) and how far every
    patch moved, gauge included (n, 6: translation, spin and plane times the radius, as the
    solve's unknowns). The solve's own step also holds a common motion the gauge takes back
    (the shift prior pulls towards the start, the gauge to the nominal places): counted, it
    looked like motion that never converges. The step's system is returned too (with its
    signal share if ``signal``); the caller drops it before the next one's build (a mosaic's
    holds a few bytes per pixel, which that build would otherwise find still held). The rows
    are weighted by ``weights`` if given (held from an earlier step, :data:`FREEZE_MOTION`),
    else by their own Cauchy weights, which the system returns with ``freeze``."""
    state, bank, base = fit.state, lv.bank, fit.base
    # scan lines as correlated noise (merge.refine.lines) only on the raw heights: smoothing
    # spreads every line's offset over its neighbours, and on the coarse levels the start's
    # misfit along lines would pass for offsets
    stats = build_normal_system(
        bank,
        cand,
        state,
        fit.noise,
        lines=lv.raw,
        signal=signal,
        weights=weights,
        keep_weights=freeze,
    )
    priors = Priors(
        plane=state.slope * bank.radius[:, None],
        plane_sigma=lv.plane_sigma,
        shift=state.s[:, :2] - (fit.start_s[:, :2] + bank.centre[:, :2] - base.centre[:, :2]),
        shift_sigma=lv.shift_sigma,
        spin=state.spin() * bank.radius,
        spin_sigma=SPIN_PRIOR * bank.radius,
    )
    delta = solve_system(stats, priors, held=lv.held)
    s0, spin0, slope0 = state.s.copy(), state.spin(), state.slope.copy()
    state.update(delta, bank.radius)
    if lv.held is None:  # held patches hold the gauge
        state.fix_gauge(bank.centre, bank.point_count)
    radius = bank.radius[:, None]
    moved = np.column_stack(
        [state.s - s0, (state.spin() - spin0)[:, None] * radius, (state.slope - slope0) * radius]
    )
    return stats.rms, moved, stats
