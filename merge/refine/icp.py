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
:mod:`merge.report.quality` the per-patch quality report, :mod:`merge.refine.level` one level's
steps and when they stop, :mod:`merge.refine.heights` the heights' last solve with every scan
line's offset (a whole mosaic's, after the last level); this module holds the schedule.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from merge.core.heightfield import Border
from merge.core.noise import patch_noise
from merge.core.overlap import span_in_patches
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.heights import solve_heights
from merge.refine.level import (
    Fit,
    Level,
    LevelSetup,
    Progress,
    run_level,
)
from merge.refine.normal_system import NormalSystem
from merge.refine.state import MosaicState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


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
#: The widest level takes no rows within two sigmas of either patch's border (its ``band``,
#: 4 px), where its smoothed heights are partly the continuation's guess with the border
#: pixel's noise doubled, wherever that leaves a run half its rows (narrower overlaps keep
#: theirs: a sliver of rows let a flat, noisy mosaic's patches claim places 28 nm off). The
#: real grating's patches, brought in along their stripes there, settle better: variations'
#: median map/floor 1.063 -> 1.006 (draw 38 1.22 -> 0.99), with narrow overlaps 1.316 -> 1.121
#: (draw 38 1.96 -> 1.10), the bench's 1.041 -> 1.031 in 17 % fewer iterations; every other
#: surface as before. The one-pixel level's band (2 px) took out the bias of its repeated
#: borders too (400 folded patches: the raw level's first step no longer shrinks the mosaic
#: by 6e-4, its Z 0.17 -> 0.05 px), but the paper grid's 50 nm ramps, whose raw level ends
#: where its path leads it, then landed 0.87 -> 0.93 nm off in XY over 10 draws.
DEFAULT_LEVELS = (
    Level(smooth=2.0, stride=2, max_iter=6, tol=0.2, band=4.0),
    Level(1.0, 2, 10, 0.05),
    Level(0.0, 1, 30, 1e-3),
)
#: On a mosaic that spans :data:`WIDE_SPAN` patches or more (:func:`span_in_patches`), the
#: smoothed levels take no rows within :data:`WIDE_BAND` pixels of either patch's border, where
#: that leaves a run half its rows (their ``band``, as the widest level's). Continued
#: point-symmetrically, a smoothed patch is bent near its border wherever the surface curves
#: (the continuation's curvature is the surface's flipped), and that shifts the pair: two noise-
#: free folded patches of 64 x 64 px, from their true places, by 0.2-1.8 nm (4 draws; within
#: 0.04 nm with the band). On average the shift is outward, and summed along a mosaic it is a
#: change of scale the raw level's first step must take back (2,500 patches: 1.47 px from one
#: side to the other, 0.37 px at the median; 10,000: twice that). From a span of about 35
#: patches that costs the raw level one more step, the dearest kind: with the band 2,500
#: patches 30.8 -> 24.9 s and 10,000 142 -> 115 s (6 -> 5 iterations), Z 1.03 -> 1.01 and
#: 0.87 -> 0.83 nm; 1,600 (a span of 30) as many iterations, Z 0.62 -> 0.61 nm. A smaller
#: mosaic's first raw step takes the scale back within the steps it needs anyway, and there
#: the border rows are kept: some surfaces need what they hold (the paper grid's 50 nm ramps in
#: 20 nm pixels settled 3-6 % worse in XY without them, above: 0.87 -> 0.90-0.93 nm over 10
#: draws at bands of 1-2 px, their raw cost rippled at the sub-pixel scale).
WIDE_SPAN = 30.0
#: The border band (pixels) of the smoothed levels on a mosaic spanning :data:`WIDE_SPAN`.
WIDE_BAND = 2.0


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
    measured: NDArray[np.bool_] | None = None,
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
        Polled every iteration; true raises :class:`~merge.core.errors.MergeCancelled`.
    first_free : (n,) bool, keyword-only
        The patches the first level moves (the others held, and only pairs with a free patch
        in the system); default all.
    measured : (n,) bool, keyword-only
        The patches the start measured in XY along both axes: the raw level holds its robust
        weights sooner where only they still move (:data:`merge.refine.level.FREEZE_MEASURED`).
        Default none (a patch slipped along a grating's stripes creeps, and so is flagged).
    held : (n,) bool, keyword-only
        Patches held at their start in every level (they hold the gauge; only pairs with a
        patch not held enter the system): a neighbourhood refined against the mosaic around it
        (:mod:`merge.live`). Default none. With none held, and a last level on the raw heights,
        the heights are solved once more with every scan line's offset
        (:func:`merge.refine.heights.solve_heights`).
    report : bool, keyword-only
        Keep, for the report (:func:`merge.report.quality.assess`), the system of the last step
        (``RefineResult.system``, built with its signal share) when that step settled the fit:
        it moved no height by :data:`~merge.refine.level.HEIGHT_TOL` of the noise, or no patch
        by the raw level's tolerance. The report then builds no system of its own at the
        transforms one such step further on (400 patches: half a second of five); a fit that
        ended otherwise (out of iterations, a stalled cost, patches held) keeps none.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    base = SurfaceBank(patches, scale, 0.0, 1)
    state = MosaicState.from_transforms(start, base, scale)
    fit = Fit(state, state.s.copy(), base, scale, patch_noise((p.noise for p in patches), scale))
    plane_sigma = np.full(2, drift_prior / scale)  # the first level: as loose along both axes
    converged = False
    unsettled = None
    wide = span_in_patches(np.array([p.footprint for p in patches])) >= WIDE_SPAN
    for li, level in enumerate(levels):
        checkpoint(0, f"refining, level {li + 1} of {len(levels)}")
        lv = _level_setup(patches, fit, pairs, li, level, first_free, held, wide=wide)
        if li == 1:
            plane_sigma = _plane_sigma(state.slope * lv.bank.radius[:, None], drift_prior / scale)
        lv = replace(
            lv, plane_sigma=plane_sigma, shift_sigma=shift_prior / scale, measured=measured
        )
        last = li == len(levels) - 1
        keep = report and last and lv.raw and held is None
        level_converged = run_level(fit, lv, level, progress=progress, cancel=cancel, keep=keep)
        if last:
            converged = level_converged
            if not converged and fit.last_step is not None:
                unsettled = fit.last_step > level.tol
    transforms = state.to_transforms(base, scale)
    if held is None and levels[-1].smooth == 0 and levels[-1].stride == 1:
        checkpoint(0, "the heights with every scan line's offset")
        lines = float(np.median([p.heights.shape[0] for p in patches]))
        prior = heights_prior(plane_sigma, drift_prior / scale, lines) * scale
        solved = solve_heights(patches, transforms, pairs, plane_sigma=(prior[0], prior[1]))
        if solved is not None:
            transforms = solved.transforms
    return RefineResult(
        transforms=transforms,
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
    *,
    wide: bool = False,
) -> LevelSetup:
    """Level ``li``'s surfaces (smoothed and strided, continued beyond the borders as
    :data:`MIRROR_FROM` says), its border band (at least :data:`WIDE_BAND` if smoothed on a
    ``wide`` mosaic) and, on the first, the patches it holds."""
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
    band = max(level.band, WIDE_BAND) if wide and not raw else level.band
    return LevelSetup(bank, level_pairs, hold, margin, raw, np.zeros(2), band=band)


def heights_prior(plane_sigma: FloatArray, drift_prior: float, lines: float) -> FloatArray:
    """The drift planes' prior sigmas (x, y; units of ``plane_sigma``) for the heights' last
    solve (:func:`merge.refine.heights.solve_heights`), which counts every overlap once: the
    last level's (``plane_sigma``, :func:`_plane_sigma`) per side of the data, times
    sqrt(:data:`SIDES`), where they hold a drift; along the lines one line's share of the
    drift across them (``lines`` per patch: the plane a drift in time leaves along a line),
    no looser than the level's. Where the planes followed the patches' own spread (wider than
    ``drift_prior``: each levelled before export) that spread stays.
    """
    sigma = np.asarray(plane_sigma, dtype=np.float64)
    spread = sigma > drift_prior
    once = np.where(spread, sigma, sigma * np.sqrt(SIDES))
    if not spread[0]:
        once[0] = min(once[0], once[1] / max(lines, 1.0))
    out: FloatArray = once
    return out


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
