"""Steps 4 and 5 of a merge: the report on the transforms the solver settled on
(:func:`judge`) and the render (:func:`finish`, which gathers both into the result; the batch
merge, :mod:`merge.pipeline`, and the live one, :mod:`merge.live`, end with it)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from merge.config import MergeConfig
from merge.core.overlap import moved_boxes, overlapping_pairs
from merge.core.patchset import Patch
from merge.core.progress import stage
from merge.records import Layout, Solution, Stopwatch
from merge.render import render_mosaic
from merge.report import (
    MergeResult,
    PatchReport,
    assess,
    holds_xy,
    patch_reports,
    unconfirmed,
    untied,
)

#: The report's word on a solution: every patch's :class:`PatchReport` and the warnings of
#: those it cannot vouch for (:func:`judge`).
Judged = tuple[list[PatchReport], list[str]]


def judge(
    patches: Sequence[Patch],
    layout: Layout,
    solution: Solution,
    cfg: MergeConfig,
    watch: Stopwatch,
) -> Judged:
    """Step 4: the report on the transforms the solver settled on."""
    transforms = solution.transforms
    with watch.step("report"), stage("report", 2, "the quality of every patch"):
        final_pairs = overlapping_pairs(moved_boxes(layout.boxes, transforms), margin=layout.cell)
        fits = assess(
            patches,
            final_pairs,
            transforms,
            bank=solution.bank,
            system=solution.system,
            plane_sigma=solution.plane_sigma,
        )
        doubted = {}
        if solution.refined_only is not None:
            which = [
                c
                for c in np.flatnonzero(solution.refined_only & layout.linked).tolist()
                if holds_xy(fits[c], patches[c])
            ]
            doubted = unconfirmed(patches, transforms, final_pairs, which, bank=solution.bank)
        loose = {}
        if solution.start_information is not None:
            loose = untied(
                patches, transforms, layout.pairs, solution.start_information, bank=solution.bank
            )
        reports, unheld = patch_reports(
            patches,
            transforms,
            fits,
            layout.linked,
            registered=cfg.method in ("default", "paper"),
            unsettled=solution.unsettled,
            unconfirmed=doubted,
            untied=loose,
        )
    return reports, unheld


def finish(
    patches: Sequence[Patch],
    layout: Layout,
    solution: Solution,
    cfg: MergeConfig,
    watch: Stopwatch,
    *,
    judged: Judged | None = None,
) -> MergeResult:
    """Steps 4 and 5: the report on the transforms the solver settled on (unless ``judged``
    already) and the render, as the result (the live merge ends with them too)."""
    transforms = solution.transforms
    reports, unheld = judged if judged is not None else judge(patches, layout, solution, cfg, watch)
    with watch.step("render"), stage("render", len(patches), "drawing the mosaic"):
        mosaic = render_mosaic(patches, transforms, pixel_size=cfg.pixel_size, feather=cfg.feather)
    return MergeResult(
        mosaic=mosaic,
        patches=reports,
        method=cfg.method,
        config=cfg,
        iterations=solution.iterations,
        converged=solution.converged,
        history=list(solution.history),
        warnings=layout.warnings + unheld,
        timings=watch.timings,
    )
