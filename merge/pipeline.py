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
   :func:`merge.finish.judge`); where it cannot vouch for the XY of a fifth of the patches,
   :func:`second_opinion` refines again from the stage's placement and keeps the better fit;
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
from merge.finish import Judged, finish, judge
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

#: Iterations a merge typically takes (9-10 from 100 to 2,500 patches): the refinement's
#: share of the progress bar.
TYPICAL_ITERATIONS = 10
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
        solution, judged = second_opinion(
            patches, layout, placed, cfg, watch, first, progress=progress, cancel=cancel
        )
    return finish(patches, layout, solution, cfg, watch, judged=judged)


#: Share of the linked patches whose XY the report cannot vouch for (not ``xy_constrained``)
#: from which the start's placement is in doubt as a whole (:func:`second_opinion`).
DOUBT_SHARE = 0.2
#: How much lower the residual RMS of the merge from the stage's placement must be to replace
#: the merge from the start's (:func:`second_opinion`).
BETTER_FIT = 0.01


def second_opinion(
    patches: Sequence[Patch],
    layout: Layout,
    placed: Placement,
    cfg: MergeConfig,
    watch: Stopwatch,
    first: tuple[Solution, Judged],
    *,
    progress: Progress | None,
    cancel: Cancel | None,
) -> tuple[Solution, Judged]:
    """Where the report cannot vouch for the XY of :data:`DOUBT_SHARE` of the linked patches
    or more, the refinement again from the stage's placement (every patch where the stage put
    it, the widest level over all of them), and the fit of the two that leaves the lower
    residual RMS, by :data:`BETTER_FIT` at least (else the ``first``, the start's).

    The start's pairs can place a whole block of patches a few cells off while claiming a
    tenth of one (a 22 x 45 px TGX1 patch's overlaps filled by ramp flanks: a correlation
    peak shifted along an edge, a tail of a ramp that is its own copy scaled), and the
    refinement then settles in the local minimum next to it, where the report finds the
    patches unconfirmed (no chain of measured overlaps ties them). The stage's placement does
    not depend on those pairs; both minima are of the same data, so the lower misfit is the
    likelier placement (of five such TGX1 draws, the fit from the true places left 4-22 %
    less residual RMS than the start's every time). Over 460 variation draws
    (``benchmarks/merge_variations.py``), at 25-50 % overlaps (draws 0-39, 500-559,
    1000-1199) TGX1's 510, 535 and 540 went from 16.6, 20.6 and 13.6 x the floor to 1.6, 1.1
    and 1.5, no draw worse (1030 and 1105 stay gross: the stage's placement leads to a
    minimum as wrong, with more misfit); at 15-25 % (draws 0-39, 500-539, 1000-1199) MoS2's
    silent patches 9 -> 2 (draw 1012 2.8 -> 1.0 x, 537 1.7 -> 1.25), TGX1's 1060 and 1195
    13 -> 1.5 and 2.5 x, and one draw worse, TGX1's 520, gross either way (17.8 -> 37 x, 8
    patches unconfirmed instead of 4).
    Restarting only the unconfirmed patches from the stage mended two of the five and left
    four silent patches on the real grating, so every patch restarts. A merge whose patches
    the report holds costs nothing more; one in doubt, a second refinement and report.
    :func:`merge_once` asks for none on a sample it said periodic: a patch a whole repeat
    off fits about as well (on the real grating the choice mended 2 gross draws and made 4
    worse)."""
    solution, judged = first
    reports = judged[0]
    linked = np.flatnonzero(layout.linked)
    doubted = sum(not reports[c].xy_constrained for c in linked.tolist())
    if not len(linked) or doubted < DOUBT_SHARE * len(linked) or not solution.history:
        return first
    stage_placed = Placement(
        [PatchTransform(centre=np.array(p.center)) for p in patches],
        ~layout.linked,
        placed.pair_information,
        placed.repeat,
    )
    done = solution.iterations

    def counted_on(iteration: int, residual: float) -> None:
        """The second fit's iterations numbered on from the first's."""
        if progress is not None:
            progress(done + iteration, residual)

    detail = "refining again from the stage's placement"
    with watch.step("second_opinion"), stage("refine", TYPICAL_ITERATIONS, detail):
        other = _solve(patches, layout, stage_placed, cfg, progress=counted_on, cancel=cancel)
    if not other.history or other.history[-1] >= (1.0 - BETTER_FIT) * solution.history[-1]:
        return first
    reports, unheld = judge(patches, layout, other, cfg, watch)
    said = (
        f"the start's placement was not borne out ({doubted} of {len(linked)} patches' XY "
        "unconfirmed after the merge from it): the merge from the stage's placement fits the "
        f"overlaps better (residual RMS {solution.history[-1] * 1e9:.2f} -> "
        f"{other.history[-1] * 1e9:.2f} nm) and is the one kept"
    )
    return other, (reports, [said, *unheld])


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
        transforms, start.xy_complete | ~layout.linked, start.pair_information, start.repeat
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
