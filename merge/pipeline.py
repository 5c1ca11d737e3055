"""``merge.run``: the stages in order, a patch set in, a merged mosaic with per-patch transforms
and quality out.

One merge is five steps over small records (:mod:`merge.records`), each timed on its own
(``MergeResult.timings``):

1. :func:`layout_of` -> :class:`Layout`: which patches can overlap (the stage's error margin), the
   cell, and warnings for patches and groups nothing ties to the rest;
2. :func:`_start` -> :class:`Placement`: the coarse start (:mod:`merge.start`), or nominal;
3. :func:`_solve` -> :class:`Solution`: the simultaneous refinement (:mod:`merge.refine`) or the
   paper's loop (:mod:`merge.paper`);
4. report: the assessment of the final transforms (:mod:`merge.report`,
   :func:`merge.finish.judge`); where it cannot vouch for the XY of a fifth of the patches, or
   the start's pairs allowed other placements, :func:`merge.opinions.second_opinion` refines
   again from those and keeps the fit with the least misfit;
5. render: one height map (:mod:`merge.render`) (:func:`merge.finish.finish` does both).

Self-calibration (``MergeConfig.self_calibrate``) wraps it: a first merge, the scanner's bend
measured from it (:mod:`merge.refine.scanner`), and where the bend stands out of the noise the
corrected patches merged again.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from merge.config import MergeConfig
from merge.core.overlap import moved_boxes, overlap_groups, overlapping_pairs
from merge.core.parallel import one_blas_thread
from merge.core.patchset import Patch, PatchSet
from merge.core.progress import Report, stage, tracking
from merge.core.transforms import PatchTransform
from merge.finish import finish, judge
from merge.opinions import TYPICAL_ITERATIONS, second_opinion
from merge.records import Layout, Placement, Solution, Stopwatch
from merge.refine import (
    DEFAULT_LEVELS,
    Level,
    estimate_distortion,
    refine,
    undistort,
)
from merge.report import MergeResult
from merge.start import coarse_cell, coarse_start
from merge.start.trust import periodic_repeat

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Called after every iteration with (iteration, residual RMS in metres).
Progress = Callable[[int, float], None]
#: Polled between iterations; returning True stops the merge with MergeCancelled.
Cancel = Callable[[], bool]

#: Prior standard deviation of a patch's XY correction in the refinement, as a fraction of the
#: searched stage error: it decides only where the data are silent (flat, 1-D structure).
SHIFT_PRIOR_FRACTION = 0.25
#: How the warning of a periodic sample begins (:func:`merge.start.trust.periodic_repeat`).
PERIODIC = "the overlaps repeat themselves"


def default_cell(patch_set: Iterable[Patch]) -> float:
    """The raster spacing: the larger pixel pitch over all patches (paper, III-C)."""
    return max(max(p.pixel_size) for p in patch_set)


def default_max_shift(patch_set: Iterable[Patch]) -> float:
    """Half the smaller side of the smallest patch."""
    return 0.5 * min(min(p.extent) for p in patch_set)


def run(
    patch_set: PatchSet,
    config: MergeConfig | None = None,
    *,
    progress: Progress | None = None,
    cancel: Cancel | None = None,
    status: Report | None = None,
) -> MergeResult:
    """Merge all patches of ``patch_set`` simultaneously into one mosaic.

    Parameters
    ----------
    patch_set : PatchSet
        Validated patches (see :func:`merge.io.manifest.read_patch_set`).
    config : MergeConfig, optional
        Method and options; defaults to ``MergeConfig()``.
    progress : callable(iteration, residual_m), keyword-only
        Called after every solver iteration.
    cancel : callable() -> bool, keyword-only
        Polled through every stage (every iteration, block of rows, pair, slab, patch); true
        stops the merge with :class:`merge.MergeCancelled`.
    status : callable(Status), keyword-only
        Told where the merge is (:class:`merge.core.progress.Status`: the stage, what within
        it, the fraction of the whole done and an ETA), at every stage and every quarter second
        (with ``self_calibrate``, the stages of each of its two merges in turn).

    With ``config.self_calibrate`` the scanner's bend shared by every patch is measured from a
    first merge, taken out of every patch, and the corrected patches are merged again: the
    result's mosaic and transforms are those of the corrected patches, and its ``distortion``
    says what was taken out (nothing, and no second merge, where no bend stands out of the
    noise). ``progress`` then counts the iterations of both merges in one sequence.
    """
    with tracking(status, cancel), one_blas_thread():
        return _run(patch_set, config or MergeConfig(), progress=progress, cancel=cancel)


def _run(
    patch_set: PatchSet,
    cfg: MergeConfig,
    *,
    progress: Progress | None,
    cancel: Cancel | None,
) -> MergeResult:
    """:func:`run` under its tracking."""
    if not cfg.self_calibrate:
        return merge_once(patch_set, cfg, progress=progress, cancel=cancel)
    clock = time.perf_counter()
    first = merge_once(patch_set, cfg, progress=progress, cancel=cancel)
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

    result = merge_once(corrected, cfg, progress=counted_on, cancel=cancel)
    result.timings.update(first_merge=spent, self_calibration=measured)
    return replace(result, distortion=distortion)


def merge_once(
    patch_set: PatchSet,
    cfg: MergeConfig,
    *,
    progress: Progress | None = None,
    cancel: Cancel | None = None,
) -> MergeResult:
    """One merge of ``patch_set`` as :func:`run` describes, without self-calibration: the five
    steps of this module's docstring, each timed under its name."""
    patches = patch_set.patches
    watch = Stopwatch()
    with watch.step("start"):
        layout = layout_of(patch_set, cfg)
        # the start's work: every patch averaged onto its lattice, every pair correlated
        with stage("start", len(patches) + len(layout.pairs), "correlating the overlaps"):
            placed = _start(patch_set, layout, cfg)
        said = []
        if placed.repeat is not None and placed.pair_information is not None:
            said = periodic_warnings(placed.repeat, placed.pair_information)
            layout = replace(layout, warnings=layout.warnings + said)
    with watch.step("solve"), stage("refine", TYPICAL_ITERATIONS, "refining"):
        solution = _solve(patches, layout, placed, cfg, progress=progress, cancel=cancel)
    judged = judge(patches, layout, solution, cfg, watch)
    # the report is done with the refinement's surfaces and system: a second opinion (or the
    # render) need not hold them beside its own
    solution = replace(solution, bank=None, system=None)
    # on a periodic sample a placement a whole repeat off fits about as well: no misfit can
    # choose between the start's and the stage's, and the start's already holds each pair to
    # the repeat nearest the stage
    if cfg.method == "default" and placed.pair_information is not None and not said:
        first = (solution, judged)

        def refit(other: Placement, counted: Progress) -> Solution:
            return _solve(patches, layout, other, cfg, progress=counted, cancel=cancel)

        solution, judged = second_opinion(
            patches, layout, placed, cfg, watch, first, refit=refit, progress=progress
        )
    return finish(patches, layout, solution, cfg, watch, judged=judged)


def layout_of(patch_set: PatchSet, cfg: MergeConfig) -> Layout:
    """Step 1: the pairs that can overlap, and warnings for what nothing ties to the rest."""
    patches = patch_set.patches
    n = len(patches)
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
    cell = cfg.cell or default_cell(patch_set)
    return Layout(boxes, pairs, linked, cell, max_shift, warnings)


def _start(patch_set: PatchSet, layout: Layout, cfg: MergeConfig) -> Placement:
    """Step 2: the coarse start (``init="auto"``), or every patch at its nominal place."""
    patches = patch_set.patches
    n = len(patches)
    if cfg.method == "nominal" or cfg.init != "auto" or not len(layout.pairs):
        return Placement([PatchTransform() for _ in range(n)], np.zeros(n, dtype=bool))
    start = coarse_start(
        patches,
        layout.pairs,
        cell=cfg.coarse_cell or coarse_cell(patch_set, layout.cell),
        max_shift=layout.max_shift,
        estimate_xy=cfg.method != "zlevel",
    )
    # a tilt the start found (scans levelled one by one) is the drift plane's start
    transforms = [
        PatchTransform(t=tc, slope=-tilt, centre=np.array(p.center))
        for tc, tilt, p in zip(start.translation, start.tilt, patches, strict=True)
    ]
    return Placement(
        transforms,
        start.xy_complete | ~layout.linked,
        start.pair_information,
        start.repeat,
        start.alternatives,
    )


def periodic_warnings(repeat: FloatArray, information: FloatArray) -> list[str]:
    """A warning where the sample's overlaps repeat themselves (:func:`periodic_repeat` of
    the start's pairs: ``repeat`` (k,) metres, ``information`` (k, 2, 2)), else none."""
    every = periodic_repeat(repeat, information)
    if not np.isfinite(every):
        return []
    return [
        f"{PERIODIC} every {every * 1e9:.0f} nm or so (a periodic sample): "
        "each pair was placed at the repeat nearest where the stage put it, so a patch the "
        f"stage put more than {0.5 * every * 1e9:.0f} nm off lies a whole repeat off, with "
        "nothing in its overlaps to show it; compare the mosaic with an image of the sample "
        "that spans several repeats (an SEM image, a wider scan)"
    ]


def _solve(
    patches: Sequence[Patch],
    layout: Layout,
    placed: Placement,
    cfg: MergeConfig,
    *,
    progress: Progress | None,
    cancel: Cancel | None,
) -> Solution:
    """Step 3: the refinement of the default method, or the paper's loop; the start as it is
    for the others."""
    if cfg.method not in ("default", "paper") or not len(layout.pairs):
        return Solution(placed.transforms)
    # pairs at the estimated places, with a margin for what the refinement may still move
    near = overlapping_pairs(moved_boxes(layout.boxes, placed.transforms), margin=4.0 * layout.cell)
    if cfg.method == "paper":
        return _paper(patches, near, placed, layout.cell, cfg, progress=progress, cancel=cancel)
    # the widest level is for patches the start left unmeasured along some direction
    levels: tuple[Level, ...] = DEFAULT_LEVELS[1:] if placed.complete else DEFAULT_LEVELS
    if cfg.max_iter is not None:
        levels = tuple(
            replace(lv, max_iter=max(1, min(lv.max_iter, cfg.max_iter))) for lv in levels
        )
    fit = refine(
        patches,
        near,
        placed.transforms,
        levels=levels,
        shift_prior=SHIFT_PRIOR_FRACTION * layout.max_shift,
        progress=progress,
        cancel=cancel,
        first_free=None if placed.complete else ~placed.measured_both,
        measured=placed.measured_both,
        report=True,
    )
    return Solution.of_refinement(
        fit,
        refined_only=None if placed.complete else ~placed.measured_both,
        start_information=placed.pair_information,
    )


def _paper(
    patches: Sequence[Patch],
    near: IntArray,
    placed: Placement,
    cell: float,
    cfg: MergeConfig,
    *,
    progress: Progress | None,
    cancel: Cancel | None,
) -> Solution:
    """The paper's GPA-ICP from the start, anchored to the nominal frame like the default."""
    from merge.paper import anchor_to_nominal, nominal_points, paper_gpa_icp  # kd-trees on demand

    paper = paper_gpa_icp(
        patches,
        near,
        np.array([tr.R for tr in placed.transforms]),
        np.array([tr.t for tr in placed.transforms]),
        cell=cell,
        max_iter=cfg.max_iter or 200,
        progress=progress,
        cancel=cancel,
    )
    nominal, owner = nominal_points(patches)
    R, t = anchor_to_nominal(nominal, owner, paper.R, paper.t)
    transforms = [PatchTransform(R[c], t[c]) for c in range(len(patches))]
    return Solution(transforms, paper.iterations, paper.converged, tuple(paper.history))
