"""The files at the merge's edges (docs/design.md): patch sets in, results out.

In: ``manifest.json`` with one height file per patch (:mod:`~merge.io.manifest`), a folder
of AFM files of any vendor format (:mod:`~merge.io.scans`, :mod:`~merge.io.formats`), or a
:class:`~merge.report.MergeResult` to write. Out: a validated :class:`~merge.core.PatchSet`,
or ``mosaic.npy``, ``mosaic.json`` and ``preview.png`` (:mod:`~merge.io.result`,
:mod:`~merge.io.preview`, :mod:`~merge.io.png`). The only package of the merge that touches the
file system; it sits above the stages, which take and return arrays.
"""

from merge.io.manifest import read_patch_set, write_patch_set
from merge.io.result import StoredResult, read_result, result_document, write_result
from merge.io.scans import read_scans, scan_files

__all__ = [
    "StoredResult",
    "read_patch_set",
    "read_result",
    "read_scans",
    "result_document",
    "scan_files",
    "write_patch_set",
    "write_result",
]
