"""The report: how well every patch fits and how well it is placed, and the merge's result.

In: the patches, their final ``T_mosaic_patch`` and the refinement's surfaces. Out: one
:class:`PatchFit` per patch (:mod:`~merge.report.quality`: correspondences, residual RMS, XY
and Z sigmas marginal over the mosaic, :mod:`~merge.report.uncertainty`), turned into
:class:`PatchReport` and gathered in :class:`MergeResult` (:mod:`~merge.report.summary`);
a patch the refinement alone placed keeps its XY only where its texture confirms the place
(:mod:`~merge.report.confirmation`), and only where a chain of overlaps that measured it ties it
to the rest (:mod:`~merge.report.ties`).
:mod:`~merge.report.evaluate` scores a mosaic against a known truth (benchmarks and tests).
"""

from merge.report.confirmation import unconfirmed
from merge.report.evaluate import Grid, Score, score_mosaic
from merge.report.quality import PatchFit, assess
from merge.report.summary import MergeResult, PatchReport, holds_xy, patch_reports
from merge.report.ties import untied
from merge.report.verdict import Verdict, verdict

__all__ = [
    "Grid",
    "MergeResult",
    "PatchFit",
    "PatchReport",
    "Score",
    "Verdict",
    "assess",
    "holds_xy",
    "patch_reports",
    "score_mosaic",
    "unconfirmed",
    "untied",
    "verdict",
]
