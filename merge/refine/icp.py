"""The default method: simultaneous GPA refinement on the full-resolution height grids.

Every patch is a continuous surface (bilinear in its own frame). For every point of a patch that
falls on another patch, the residual is its height above that surface, linearised on the
surface's tangent plane (point-to-plane, the plane taken from the height map's slopes at the
sub-pixel foot of the point, so correspondences are sub-cell; heights, not distances along the
normal, since heights are what the noise is in). All 6 rigid degrees of freedom of all patches are
solved together, every Gauss-Newton step, from one sparse normal system: this is the Generalized
Procrustes objective — the sum over every overlap point of its squared distances to the other
patches is, up to a factor, its squared distance to their mean — never a chain of pairwise
alignments.

The six unknowns of a patch are its translation (3), its rotation about z and an in-patch drift
term: a Z plane (dz/dx, dz/dy) that moves heights only. A linear Z drift during the scan is such
a plane; modelling it as a tilt of a rigid body instead would couple heights to XY (a tilt of
1 mrad shears the top of a 600 nm step 0.6 nm against its foot), and noise on steep edges would
then leak into both.

Coarse to fine: the first two levels work on every second point of heights smoothed by two
pixels, then one, which widens the basin of convergence; the last on the raw heights at every
point. The widest level matters (and the pipeline asks for it) only where the coarse start left a
direction unmeasured: along the stripes of a 1-D grating a patch starts from its stage error,
and only the stripes' slight bends and defects, tens of nanometres wide, can bring it in. So it
moves only those patches (``first_free``), against their neighbours held where the start put
them, on their pairs alone (the gauge is then held by the others): on TGX1, where a few flat-face
patches are such, it cost as much as a level over all (the solve 1.0-1.1 -> 0.64-0.78 s of 50
patches, every bench draw's result within 0.01 map/floor).
Residuals are re-weighted with a Cauchy function of their robust scale, so tip artefacts, dust
or a changed surface do not pull the solution.

Gauge: after every step the common motion of all patches (rotation about z, a Z plane and a
translation — none changes any residual) is removed: the mean rotation and mean drift plane are
zero, and the patch points move on average by zero from their nominal places
(:meth:`merge.refine.state.MosaicState.fix_gauge`), so the mosaic cannot drift away from the
stage frame.

Pieces: :mod:`merge.refine.bank` holds the patches as surfaces,
:mod:`merge.refine.normal_system` builds the Gauss-Newton system and :mod:`merge.refine.solve`
solves it, :mod:`merge.refine.state` holds the placement of every patch and its gauge,
:mod:`merge.report.quality` the per-patch quality report; this module holds the schedule.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from merge.core.errors import MergeCancelled
from merge.core.heightfield import Border
from merge.core.noise import patch_noise
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.convergence import height_effect, remaining, slope_rms
from merge.refine.normal_system import NormalSystem, build_normal_system
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
#: Expected in-patch Z drift (metres, centre to corner) of the drift-plane prior.
DRIFT_PRIOR = 5e-9
#: Share of the drift prior along the fast axis (x). A Z drift in time tilts a patch along its
#: slow axis; along a line it moves by one line's share (1 / lines, a few per cent). Overlaps
#: measure neighbours' relative tilts, but across a narrow overlap only weakly: left free, these
#: weak differences add up to a mosaic-wide bowl (on TGX1 draw 0, 0.4 nm per µm² in x²; Z error
#: 0.60 -> 0.51 nm without it). A tenth leaves room for what the plane does not model (a bow).
FAST_DRIFT_SHARE = 0.1
#: Patches' worth of weight the physical bound on the drift planes has against the spread of
#: the planes a mosaic's first level found (:func:`_plane_sigma`). The prior is what holds a
#: large mosaic's weakly measured bend (the patch rows' relative tilts): set by the drift a
#: mosaic shows, and counted per side of the data, 400 folded patches of 64 x 64 px (8 draws)
#: Z 0.70 -> 0.53 nm, map/floor 1.031 -> 1.017 (the Cramér-Rao bound's Z with the drift's own
#: prior: 0.51); 100 of 256 x 256 px (6 draws) Z 0.29 -> 0.27, 400 (4 draws) 0.46 -> 0.42.
PLANE_PSEUDO = 10
#: How often the data count every overlap: once from each side (a run per directed pair), both
#: sides reading the same two scans' noise. A prior that says what a patch's physics allows (the
#: drift planes' from the second level on) enters as often, or the data outweigh it twice over.
#: The other priors are limits on where a patch may wander, not physics, and enter once: the
#: shift and spin priors; the first level's planes, which must find what tilts the patches have;
#: planes spread wider than a drift (levelled one by one: held twice as hard, twelve patches
#: around a 600 nm step ended 59 nm off in XY instead of 2).
SIDES = 2.0
#: Standard deviation (radians) of the prior on a patch's rotation about z.
SPIN_PRIOR = np.radians(2.0)
#: Smoothing (pixels) from which the first level continues patches point-symmetrically beyond
#: their borders; the later levels always do (see :class:`merge.refine.bank.SurfaceBank`). Patches
#: overlap along their borders, so a bias there is a bias of every pair: repeating the border
#: value bends a slope that crosses it by a good fraction of slope x sigma. Where the widest
#: level brings in patches the start left unmeasured along a grating's stripes that bias
#: dominates (grid-real draws 21-30, median XY 2.7 -> 2.0 nm); the one-pixel level after it,
#: too (draws 0-5 and 21-30, median 3.56 -> 2.25 nm, draw 25 5.8 -> 2.2; TGX1, MoS2, folded as
#: before). But the first level's drift planes are free (their spread sets the prior of the
#: next, :func:`_plane_sigma`), and at one pixel the continuation's doubled border noise tilts
#: them: 20 x 20 folded patches, x planes spread 0.03 -> 0.10 px, Z 0.77 -> 2.32 nm, as the raw
#: level stops before it has flattened them. A plane fitted locally at the border instead did
#: worse on the grating (2.44 nm, draw 25 7.0): its one-sided window feels the stripes' curvature.
MIRROR_FROM = 1.5
#: The widest level only brings patches into the next one's reach (a pixel or so): it stops
#: once no patch moves a fifth of a pixel (at 0.05 px TGX1 ran all six iterations, its
#: unmeasured patches wandering by 0.08 px; every case's result the same either way, two
#: iterations fewer). The one-pixel level keeps 0.05: at 0.1 the grating's patches, creeping
#: along the stripes, stopped short (draws 1 and 4: XY 1.9 -> 2.4 nm).
DEFAULT_LEVELS = (
    Level(smooth=2.0, stride=2, max_iter=6, tol=0.2),
    Level(1.0, 2, 10, 0.05),
    Level(0.0, 1, 30, 1e-3),
)


@dataclass(frozen=True)
class RefineResult:
    """``T_mosaic_patch`` per patch, iterations and the residual RMS of each; ``bank``, the patches'
    raw heights as surfaces (for :func:`merge.report.quality.assess`, which needs the same);
    ``system``, with ``report=True``, the last step's system with its signal share when that
    step settled the fit (:func:`refine`), else None; ``plane_sigma`` (2,), the drift planes'
    prior of the last level as its steps weighed it (x, y; pixel units, times each patch's
    radius: :class:`merge.refine.solve.Priors`), which the report counts as they did;
    ``unsettled`` (n,), where the last level ran out of iterations, the patches its last step
    still moved in the plane by more than its tolerance (their XY is where the fit stopped, not
    an optimum), else None."""

    transforms: list[PatchTransform]
    iterations: int
    converged: bool
    history: list[float]
    bank: SurfaceBank
    system: NormalSystem | None = None
    plane_sigma: FloatArray | None = None
    unsettled: NDArray[np.bool_] | None = None


@dataclass
class Fit:
    """What the refinement carries from level to level: the placement of every patch
    (``state``, pixel units of ``scale`` metres), where the start put it (``start_s``), the
    raw surfaces (``base``), the height noise (pixel units), and the iterations so far with the
    residual RMS (metres) of each; how far the last step moved every patch in the plane
    (``last_step`` (n,), pixels: XY and spin times the radius)."""

    state: MosaicState
    start_s: FloatArray
    base: SurfaceBank
    scale: float
    noise: float
    iteration: int = 0
    history: list[float] = field(default_factory=list)
    system: NormalSystem | None = None
    last_step: FloatArray | None = None


@dataclass(frozen=True)
class LevelSetup:
    """One level's surfaces and system: ``bank``; the pairs in it and the patches ``held``
    (None: none); the look-up ``margin`` (pixels); whether it works on the raw heights; the
    priors' sigmas of the drift planes (x, y) and of the XY shifts (pixel units)."""

    bank: SurfaceBank
    pairs: IntArray
    held: NDArray[np.bool_] | None
    margin: float
    raw: bool
    plane_sigma: FloatArray
    shift_sigma: float = np.inf


def refine(
    patches: Sequence[Patch],
    pairs: IntArray,
    start: Sequence[PatchTransform],
    *,
    levels: Sequence[Level] = DEFAULT_LEVELS,
    drift_prior: float = DRIFT_PRIOR,
    shift_prior: float = np.inf,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    first_free: NDArray[np.bool_] | None = None,
    held: NDArray[np.bool_] | None = None,
    report: bool = False,
) -> RefineResult:
    """Refine all patch transforms at once.

    Parameters
    ----------
    patches : sequence of Patch
    pairs : (k, 2) int array
        Patch pairs that may overlap.
    start : sequence of PatchTransform
        Initial ``T_mosaic_patch`` per patch.
    levels : sequence of Level, keyword-only
        Coarse-to-fine schedule.
    drift_prior : float, keyword-only
        Largest expected in-patch Z drift, metres from the patch centre to its corner (a
        Gaussian prior on the drift plane; along the fast axis :data:`FAST_DRIFT_SHARE` of it;
        from the second level on, the drift the first level's planes show, within that bound:
        :func:`_plane_sigma`).
        Overlaps pin down the differences of neighbouring planes well but a mosaic-wide bend
        only weakly; the prior keeps that bend out.
    shift_prior : float, keyword-only
        Standard deviation (metres) of a prior holding each patch's XY near its start. It only
        matters where the data do not constrain XY (a flat overlap, the stripes of a 1-D
        grating): there the patch stays at its start instead of wandering off.
    progress : callable(iteration, residual_rms_m), keyword-only
        Called after every iteration.
    cancel : callable() -> bool, keyword-only
        Polled every iteration; true raises :class:`MergeCancelled`.
    first_free : (n,) bool, keyword-only
        The patches the first level moves (the others held, and only pairs with a free patch
        in the system); default all.
    held : (n,) bool, keyword-only
        Patches held at their start in every level (they hold the gauge; only pairs with a
        patch not held enter the system): a neighbourhood refined against the mosaic around it
        (:mod:`merge.live`). Default none.
    report : bool, keyword-only
        Keep, for the report (:func:`merge.report.quality.assess`), the system of the last step
        (``RefineResult.system``, built with its signal share) when that step settled the fit:
        it moved no height by :data:`HEIGHT_TOL` of the noise, or no patch by the raw level's
        tolerance. The report then builds no system of its own at the transforms one such step
        further on (400 patches: half a second of five); a fit that ended otherwise (out of
        iterations, a stalled cost, patches held) keeps none.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    base = SurfaceBank(patches, scale, 0.0, 1)
    state = MosaicState.from_transforms(start, base, scale)
    fit = Fit(state, state.s.copy(), base, scale, patch_noise((p.noise for p in patches), scale))
    plane_sigma = np.full(2, drift_prior / scale)  # the first level: as loose along both axes
    converged = False
    unsettled = None
    for li, level in enumerate(levels):
        checkpoint(0, f"refining, level {li + 1} of {len(levels)}")
        lv = _level_setup(patches, fit, pairs, li, level, first_free, held)
        if li == 1:
            plane_sigma = _plane_sigma(state.slope * lv.bank.radius[:, None], drift_prior / scale)
        lv = replace(lv, plane_sigma=plane_sigma, shift_sigma=shift_prior / scale)
        last = li == len(levels) - 1
        keep = report and last and lv.raw and held is None
        level_converged = _run_level(fit, lv, level, progress=progress, cancel=cancel, keep=keep)
        if last:
            converged = level_converged
            if not converged and fit.last_step is not None:
                unsettled = fit.last_step > level.tol
    return RefineResult(
        transforms=state.to_transforms(base, scale),
        iterations=fit.iteration,
        converged=converged,
        history=fit.history,
        bank=base,
        system=fit.system,
        plane_sigma=plane_sigma.copy(),
        unsettled=unsettled,
    )


def _level_setup(
    patches: Sequence[Patch],
    fit: Fit,
    pairs: IntArray,
    li: int,
    level: Level,
    first_free: NDArray[np.bool_] | None,
    held: NDArray[np.bool_] | None,
) -> LevelSetup:
    """Level ``li``'s surfaces (smoothed and strided, continued beyond the borders as
    :data:`MIRROR_FROM` says) and, on the first, the patches it holds."""
    raw = level.smooth == 0 and level.stride == 1
    border: Border = "mirror" if li > 0 or level.smooth >= MIRROR_FROM else "repeat"
    bank = (
        fit.base
        if raw
        else SurfaceBank(patches, fit.scale, level.smooth, level.stride, border=border)
    )
    margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
    hold = held
    if li == 0 and first_free is not None and not first_free.all():
        hold = ~first_free if held is None else held | ~first_free
    level_pairs = pairs if hold is None else pairs[(~hold)[pairs].any(axis=1)]
    return LevelSetup(bank, level_pairs, hold, margin, raw, np.zeros(2))


def _run_level(
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
    one's is kept in ``fit.system`` if that step settled the level (:func:`refine`'s
    ``report``)."""
    state, bank = fit.state, lv.bank
    cand = bank.candidates(lv.pairs, state.R, state.s, lv.margin)
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
    for step in range(level.max_iter):
        if cancel is not None and cancel():
            raise MergeCancelled("merge cancelled")
        checkpoint()
        if moved > 0.5 * lv.margin:
            cand, moved = bank.candidates(lv.pairs, state.R, state.s, lv.margin), 0.0
        fit.system = None  # a step's system is dropped before the next one is built
        # the level's first step is never the last but where no patch moves: its system goes
        # without the signal share, which costs a tenth of a build
        signal = keep and step > 0
        rms, delta, stats = _step(fit, lv, cand, signal=signal)
        fit.system = stats if signal else None
        del stats
        last_motion = motion if step > 1 else np.inf
        motion = float(
            (np.abs(delta[:, :3]).max(axis=1) + np.abs(delta[:, 3:]).max(axis=1)).max(initial=0)
        )
        moved += motion
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
        # the level's first step moves from the last level's optimum to this one's (smoothing
        # and stride change it): no ratio of convergence to extrapolate from
        last_effect = effect if step > 1 else np.inf
        effect = height_effect(delta, slope)
        settled = remaining(effect, last_effect) < HEIGHT_TOL * fit.noise
        # the motion still to come, as the heights' (a level of 3,600 patches, smoothed: steps
        # of 0.69, 0.087 and 0.023 px, where the second's tail was 0.012 px, within the 0.05
        # of the level's tolerance; the largest motion of many patches grows with their number)
        if remaining(motion, last_motion) < level.tol or settled:
            return True  # the report's system (if kept) is this step's
        if stalls >= STALLS:
            fit.system = None  # the last step may have moved patches along a flat overlap
            return True
    fit.system = None
    return False


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
    fit: Fit, lv: LevelSetup, cand: Runs, *, signal: bool = False
) -> tuple[float, FloatArray, NormalSystem]:
    """One Gauss-Newton step of every patch not held: the system at the current placement, its
    priors, the solve, the move and the gauge; the residual RMS (pixel units) and how far every
    patch moved, gauge included (n, 6: translation, spin and plane times the radius, as the
    solve's unknowns). The solve's own step also holds a common motion the gauge takes back
    (the shift prior pulls towards the start, the gauge to the nominal places): counted, it
    looked like motion that never converges. The step's system is returned too (with its
    signal share if ``signal``); the caller drops it before the next one's build (a mosaic's
    holds a few bytes per pixel, which that build would otherwise find still held)."""
    state, bank, base = fit.state, lv.bank, fit.base
    # scan lines as correlated noise (merge.refine.lines) only on the raw heights: smoothing
    # spreads every line's offset over its neighbours, and on the coarse levels the start's
    # misfit along lines would pass for offsets
    stats = build_normal_system(bank, cand, state, fit.noise, lines=lv.raw, signal=signal)
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


def _plane_sigma(plane: FloatArray, drift_prior: float) -> FloatArray:
    """Prior sigmas (x, y) of the drift planes (n, 2), both times the patch radius (pixels).

    Physics bounds them: :data:`FAST_DRIFT_SHARE` of ``drift_prior`` along the lines, all of it
    across. Within that bound the planes the first level found say how large this instrument's
    drift is: their spread, pooled with the bound as :data:`PLANE_PSEUDO` patches' worth (an
    inverse-gamma prior on the variance; a handful of patches say little, a mosaic says it
    all). The first level's planes are held loosely, so the spread is the drift's own plus that
    level's noise: too wide, if anything. But where the planes spread more than ``drift_prior``
    along an axis, the patches' tilts are not a drift in time (each patch levelled on its own
    before export, a scanner's bow), and a prior as tight would bend the mosaic to flatten
    them: there the prior follows their spread. The drift's prior enters once per side of the
    data (:data:`SIDES`), a limit once.
    """
    physics = np.array([FAST_DRIFT_SHARE, 1.0]) * drift_prior
    n = len(plane)
    spread2 = np.mean(plane**2, axis=0) if n else np.zeros(2)
    pooled = np.sqrt((PLANE_PSEUDO * physics**2 + n * spread2) / (PLANE_PSEUDO + n))
    spread = np.sqrt(spread2)
    drift = np.minimum(pooled, physics) / np.sqrt(SIDES)
    out: FloatArray = np.where(spread > drift_prior, spread, drift)
    return out
