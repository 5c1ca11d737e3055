"""The GPA-ICP merge engine: overlapping AFM patches in, one drift-free topography out.

Pure numpy/scipy, laid out as its pipeline (:mod:`merge.pipeline` runs the stages in order):

* :mod:`merge.core` — the vocabulary every stage shares (patches, transforms, grids, noise);
* :mod:`merge.start` — the coarse start from correlated overlaps;
* :mod:`merge.refine` — the simultaneous refinement (and the scanner's self-calibration);
* :mod:`merge.report` — per-patch quality and uncertainty, the result;
* :mod:`merge.render` — the patches through their transforms onto one grid;
* :mod:`merge.paper` — the paper's literal method, apart;
* :mod:`merge.live` — the same stages patch by patch while a run scans, and the quality gate;
* :mod:`merge.io` — patch-set and result files, at the edge.

The entry points:

* :func:`merge.run` — merge a :class:`PatchSet` with a :class:`MergeConfig`;
* :func:`merge.read_patch_set` / :func:`merge.write_result` — the file formats of docs/design.md;
* :func:`merge.read_scans` — a folder of scans from any AFM, placed by their offsets.
"""

from merge.config import METHODS, MergeConfig
from merge.core import MergeCancelled, Patch, PatchSet, PatchSetError, PatchTransform
from merge.core.progress import Status
from merge.io import (
    StoredResult,
    read_patch_set,
    read_result,
    read_scans,
    write_patch_set,
    write_result,
)
from merge.pipeline import run
from merge.render import Mosaic, render_mosaic
from merge.report import MergeResult, PatchReport

__all__ = [
    "METHODS",
    "MergeCancelled",
    "MergeConfig",
    "MergeResult",
    "Mosaic",
    "Patch",
    "PatchReport",
    "PatchSet",
    "PatchSetError",
    "PatchTransform",
    "Status",
    "StoredResult",
    "read_patch_set",
    "read_result",
    "read_scans",
    "render_mosaic",
    "run",
    "write_patch_set",
    "write_result",
]
