"""``merge.run``: a patch set in, a merged mosaic with per-patch transforms and quality out."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from merge.bank import SurfaceBank
from merge.coarse import coarse_start
from merge.config import MergeConfig
from merge.downsample import grid_downsample
from merge.gauge import anchor_to_nominal, nominal_points
from merge.lattice import coherence, fill_empty_lines
from merge.overlap import moved_boxes, overlap_groups, overlapping_pairs
from merge.patchset import PatchSet
from merge.quality import assess
from merge.refine import DEFAULT_LEVELS, Level, refine
from merge.render import Mosaic, render_mosaic
from merge.scanner import ScanDistortion, estimate_distortion, undistort
from merge.transforms import PatchTransform

FloatArray = NDArray[np.float64]

#: Called after every iteration with (iteration, residual RMS in metres).
Progress = Callable[[int, float], None]
#: Polled between iterations; returning True stops the merge with MergeCancelled.
Cancel = Callable[[], bool]

#: An XY standard deviation above this fraction of the pixel pitch means "XY not constrained".
XY_CONSTRAINED_FRACTION = 0.25


@dataclass(frozen=True)
class PatchReport:
    """What the merge did to one patch and how well it fits.

    transform : ``T_mosaic_patch`` (rigid motion plus in-patch drift plane, metres).
    rotation, translation : the rigid transform closest to ``transform`` over the patch's points,
        for consumers that only understand ``q = R p + t``.
    overlaps : whether any other patch can overlap it (otherwise it stays nominal).
    correspondences : overlap points that entered the fit.
    residual_rms : RMS normal distance of those points to the other patches, metres.
    xy_constrained : whether its own overlaps pin down XY (a flat overlap constrains only Z).
    xy_sigma, z_sigma : standard deviations of its translation (XY: the larger axis), metres,
        marginal over the whole mosaic with its common motion fixed: a block of patches tied to
        the rest by little texture is as uncertain as the block (:mod:`merge.uncertainty`).
    """

    id: str
    transform: PatchTransform
    rotation: FloatArray
    translation: FloatArray
    overlaps: bool
    correspondences: int
    residual_rms: float
    xy_constrained: bool
    xy_sigma: float
    z_sigma: float


@dataclass(frozen=True)
class MergeResult:
    """The mosaic, every patch's transform and quality, and how the solver went."""

    mosaic: Mosaic
    patches: list[PatchReport]
    method: str
    config: MergeConfig
    iterations: int
    converged: bool
    history: list[float]
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    #: the scanner's bend taken out of every patch (``MergeConfig.self_calibrate``), or None
    distortion: ScanDistortion | None = None

    @property
    def transforms(self) -> list[PatchTransform]:
        """``T_mosaic_patch`` in patch order."""
        return [p.transform for p in self.patches]


def default_cell(patch_set: PatchSet) -> float:
    """The raster spacing: the larger pixel pitch over all patches (paper, III-C)."""
    return max(max(p.pixel_size) for p in patch_set)


#: Prior standard deviation of a patch's XY correction in the refinement, as a fraction of the
#: searched stage error: it decides only where the data are silent (flat, 1-D structure).
SHIFT_PRIOR_FRACTION = 0.25

#: The coarse start correlates patches of at least about this many cells along their shorter
#: side.
COARSE_CELLS = 32
#: Cells of all patches together the coarse start may correlate on: below it, finer cells.
COARSE_BUDGET = 150_000
#: Median structure-tensor coherence of the patches from which a sample is one-dimensional (a
#: grating: 0.99 in every patch; TGX1 0.3-0.8, MoS2 0.2, the folded surface 0.3, roughness
#: 0.03): it keeps the coarser lattice.
ONE_DIMENSIONAL = 0.95


def coarse_cell(patch_set: PatchSet, cell: float) -> float:
    """The cell of the coarse start: the finer of ``cell`` and the finest pixel pitch (so that
    texture along the fine axis of oblong pixels survives) times a whole factor.

    The factor brings the smaller patch side down to about :data:`COARSE_CELLS` cells (the
    start needs about a pixel of precision, not better), or, where the patches hold fewer
    cells than :data:`COARSE_BUDGET` at a smaller one, to that: texture finer than the cell is
    lost to the start. On a grating's flat faces the only texture is a roughness of ~25 nm;
    cut into 1 µm patches of 200 pixels, 32 cells (31 nm) left the overlaps there to chance
    peaks (bench case tgx1-1um: 5 draws of 8 within 1.5 x the floor, 2 of 10 more off by tens
    of nanometres; at 15 nm 8 of 8 and 10 of 10). Not on a
    one-dimensional sample (:data:`ONE_DIMENSIONAL`): along a grating's stripes finer cells
    resolve noise and defects, whose peaks a stripe-width apart are as likely (the real
    grating, 2 draws of 16 off by 10-90 nm at its pixel pitch).
    """
    side = min(min(p.extent) for p in patch_set)
    fine = min(min(p.pixel_size) for p in patch_set)
    base = min(fine, cell)
    coarsest = max(1, round(side / base / COARSE_CELLS))
    cells = sum(p.extent[0] * p.extent[1] for p in patch_set) / base**2
    finest = max(1, math.ceil(math.sqrt(cells / COARSE_BUDGET)))
    if finest < coarsest and not _one_dimensional(patch_set, base * coarsest):
        return base * finest
    return base * coarsest


def _one_dimensional(patch_set: PatchSet, cell: float) -> bool:
    """Whether the patches, averaged onto ``cell``, show one-dimensional structure (stripes)."""
    grids = [
        fill_empty_lines(grid_downsample(p.heights, p.pixel_size, cell=cell, origin=p.origin))
        for p in patch_set
    ]
    return float(np.median([coherence(g.heights) for g in grids])) >= ONE_DIMENSIONAL


def default_max_shift(patch_set: PatchSet) -> float:
    """Half the smaller side of the smallest patch."""
    return 0.5 * min(min(p.extent) for p in patch_set)


def run(
    patch_set: PatchSet,
    config: MergeConfig | None = None,
    *,
    progress: Progress | None = None,
    cancel: Cancel | None = None,
) -> MergeResult:
    """Merge all patches of ``patch_set`` simultaneously into one mosaic.

    Parameters
    ----------
    patch_set : PatchSet
        Validated patches (see :func:`merge.manifest.read_patch_set`).
    config : MergeConfig, optional
        Method and options; defaults to ``MergeConfig()``.
    progress : callable(iteration, residual_m), keyword-only
        Called after every solver iteration.
    cancel : callable() -> bool, keyword-only
        Polled every iteration; true stops the merge with :class:`merge.MergeCancelled`.

    With ``config.self_calibrate`` the scanner's bend shared by every patch is measured from a
    first merge, taken out of every patch, and the corrected patches are merged again: the
    result's mosaic and transforms are those of the corrected patches, and its ``distortion``
    says what was taken out (nothing, and no second merge, where no bend stands out of the
    noise). ``progress`` then counts the iterations of both merges in one sequence.
    """
    cfg = config or MergeConfig()
    if not cfg.self_calibrate:
        return _merge(patch_set, cfg, progress=progress, cancel=cancel)
    clock = time.perf_counter()
    first = _merge(patch_set, cfg, progress=progress, cancel=cancel)
    spent = time.perf_counter() - clock
    distortion = estimate_distortion(patch_set.patches, first.transforms)
    if distortion is None:
        first.warnings.append(
            "self-calibration needs scans of one size and pixel count; the patches differ, "
            "so no scanner bend was taken out"
        )
        return first
    measured = time.perf_counter() - clock - spent
    if not any(distortion.significant):  # a straight scanner: the first merge stands
        first.timings.update(self_calibration=measured)
        return replace(first, distortion=distortion)
    corrected = PatchSet(undistort(p, distortion) for p in patch_set)

    def counted_on(iteration: int, residual: float) -> None:
        """The second merge's iterations numbered on from the first's."""
        if progress is not None:
            progress(first.iterations + iteration, residual)

    result = _merge(corrected, cfg, progress=counted_on, cancel=cancel)
    result.timings.update(first_merge=spent, self_calibration=measured)
    return replace(result, distortion=distortion)


def _merge(
    patch_set: PatchSet,
    cfg: MergeConfig,
    *,
    progress: Progress | None,
    cancel: Cancel | None,
) -> MergeResult:
    """One merge of ``patch_set`` as :func:`run` describes (without self-calibration)."""
    patches = patch_set.patches
    n = len(patches)
    clock = time.perf_counter()
    timings: dict[str, float] = {}
    cell = cfg.cell or default_cell(patch_set)
    max_shift = cfg.max_shift or default_max_shift(patch_set)
    boxes = np.array([p.footprint for p in patches])
    pairs = overlapping_pairs(boxes, margin=max_shift)
    linked = np.zeros(n, dtype=bool)
    linked[pairs.ravel()] = True
    warnings = [
        f"patch {patches[c].id!r} overlaps no other patch: it stays at its nominal place"
        for c in np.flatnonzero(~linked)
    ]
    label = overlap_groups(pairs, n)
    groups = [np.flatnonzero(label == g) for g in np.unique(label[linked])]
    if len(groups) > 1:
        firsts = ", ".join(repr(patches[int(g[0])].id) for g in groups)
        warnings.append(
            f"the patches form {len(groups)} groups that do not overlap each other (those of "
            f"{firsts}): each is merged on its own; where they lie against each other is the "
            "stage's placement, not a measurement"
        )
    transforms = [PatchTransform() for _ in range(n)]
    complete = False
    measured_both = np.zeros(n, dtype=bool)  # patches whose XY the start measured both ways
    if cfg.method != "nominal" and cfg.init == "auto" and len(pairs):
        start = coarse_start(
            patches,
            pairs,
            cell=cfg.coarse_cell or coarse_cell(patch_set, cell),
            max_shift=max_shift,
            estimate_xy=cfg.method != "zlevel",
        )
        # a tilt the start found (scans levelled one by one) is the drift plane's start
        transforms = [
            PatchTransform(t=tc, slope=-tilt, centre=np.array(p.center))
            for tc, tilt, p in zip(start.translation, start.tilt, patches, strict=True)
        ]
        measured_both = start.xy_complete | ~linked
        complete = bool(measured_both.all())
    timings["start"] = time.perf_counter() - clock
    iterations, converged, history = 0, True, []
    raw: SurfaceBank | None = None  # the refinement's surfaces, reused by the assessment
    if cfg.method in ("default", "paper") and len(pairs):
        # pairs at the estimated places, with a margin for what the refinement may still move
        near = overlapping_pairs(moved_boxes(boxes, transforms), margin=4.0 * cell)
        if cfg.method == "default":
            # the widest level is for patches the start left unmeasured along some direction
            levels: tuple[Level, ...] = DEFAULT_LEVELS[1:] if complete else DEFAULT_LEVELS
            if cfg.max_iter is not None:
                levels = tuple(
                    Level(lv.smooth, lv.stride, max(1, min(lv.max_iter, cfg.max_iter)), lv.tol)
                    for lv in levels
                )
            fit = refine(
                patches,
                near,
                transforms,
                levels=levels,
                shift_prior=SHIFT_PRIOR_FRACTION * max_shift,
                progress=progress,
                cancel=cancel,
                first_free=None if complete else ~measured_both,
            )
            transforms, raw = fit.transforms, fit.bank
            iterations, converged, history = fit.iterations, fit.converged, fit.history
        else:
            R0 = np.array([tr.R for tr in transforms])
            t0 = np.array([tr.t for tr in transforms])
            from merge.paper import paper_gpa_icp  # its kd-trees' import only when asked for

            paper = paper_gpa_icp(
                patches,
                near,
                R0,
                t0,
                cell=cell,
                max_iter=cfg.max_iter or 200,
                progress=progress,
                cancel=cancel,
            )
            nominal, owner = nominal_points(patches)
            R, t = anchor_to_nominal(nominal, owner, paper.R, paper.t)
            transforms = [PatchTransform(R[c], t[c]) for c in range(n)]
            iterations, converged, history = paper.iterations, paper.converged, paper.history
    timings["solve"] = time.perf_counter() - clock - timings["start"]
    final_pairs = overlapping_pairs(moved_boxes(boxes, transforms), margin=cell)
    fits = assess(patches, final_pairs, transforms, bank=raw)
    reports = []
    for c, p in enumerate(patches):
        f = fits[c]
        held = f.xy_sigma_local < XY_CONSTRAINED_FRACTION * min(p.pixel_size)
        xy_ok = f.correspondences > 0 and held
        xx, yy = p.pixel_coordinates()
        sample = np.column_stack([xx.ravel(), yy.ravel(), p.heights.ravel()])[::7]
        R_rigid, t_rigid = transforms[c].rigid_approximation(sample[np.isfinite(sample[:, 2])])
        reports.append(
            PatchReport(
                id=p.id,
                transform=transforms[c],
                rotation=R_rigid,
                translation=t_rigid,
                overlaps=bool(linked[c]),
                correspondences=f.correspondences,
                residual_rms=f.residual_rms,
                xy_constrained=bool(xy_ok),
                xy_sigma=f.xy_sigma,
                z_sigma=f.z_sigma,
            )
        )
        if linked[c] and not xy_ok and cfg.method in ("default", "paper"):
            warnings.append(
                f"patch {p.id!r}: its overlaps constrain Z but not XY (too flat or a 1-D "
                "structure); its XY there is a guess, not a measurement"
            )
    mosaic = render_mosaic(patches, transforms, pixel_size=cfg.pixel_size, feather=cfg.feather)
    timings["render"] = time.perf_counter() - clock - timings["start"] - timings["solve"]
    return MergeResult(
        mosaic=mosaic,
        patches=reports,
        method=cfg.method,
        config=cfg,
        iterations=iterations,
        converged=converged,
        history=history,
        warnings=warnings,
        timings=timings,
    )
