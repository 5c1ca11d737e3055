"""The GPA-ICP merge engine: overlapping AFM patches in, one drift-free topography out.

Pure numpy/scipy. The entry points:

* :func:`merge.run` — merge a :class:`PatchSet` with a :class:`MergeConfig`;
* :func:`merge.read_patch_set` / :func:`merge.write_result` — the file formats of DESIGN.md.
"""

from merge.config import METHODS, MergeConfig
from merge.engine import MergeResult, PatchReport, run
from merge.errors import MergeCancelled, PatchSetError
from merge.manifest import read_patch_set, write_patch_set
from merge.patchset import Patch, PatchSet
from merge.render import Mosaic, render_mosaic
from merge.result import StoredResult, read_result, write_result
from merge.transforms import PatchTransform

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
    "StoredResult",
    "read_patch_set",
    "read_result",
    "render_mosaic",
    "run",
    "write_patch_set",
    "write_result",
]
