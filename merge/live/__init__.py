"""The live merge: a mosaic merged patch by patch while it is scanned, and each patch judged.

In: patches one at a time (:class:`merge.core.Patch`), as the instrument stores them, and
what the scan recorded of each. Out: after every addition, the transforms of the patches it
moved and the quality of its neighbourhood (:class:`LiveUpdate`), the live mosaic on demand,
a verdict per patch (:class:`Gate`: keep it, or scan it again and why), and at the end the
same :class:`merge.report.MergeResult` a batch merge gives.
"""

from merge.live.canvas import LiveCanvas
from merge.live.gate import Gate, ScanRecord, Verdict, record_verdict
from merge.live.incremental import FULL_EVERY, LiveMerge, LiveUpdate

__all__ = [
    "FULL_EVERY",
    "Gate",
    "LiveCanvas",
    "LiveMerge",
    "LiveUpdate",
    "ScanRecord",
    "Verdict",
    "record_verdict",
]
