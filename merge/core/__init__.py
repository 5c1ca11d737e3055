"""The vocabulary every stage shares: patches, transforms, grids, noise and overlaps.

In: nothing of the merge (numpy and scipy only). Out: the data passed between the stages
(:class:`Patch`, :class:`PatchSet`, :class:`PatchTransform` ``T_mosaic_patch``), the errors,
and the pure kernels more than one stage stands on: height fields as surfaces
(:mod:`~merge.core.heightfield`), grid down-sampling (:mod:`~merge.core.downsample`), the
noise of a scan (:mod:`~merge.core.noise`), which footprints overlap
(:mod:`~merge.core.overlap`), information with the noise's share taken out
(:mod:`~merge.core.information`), the weighted rigid transform (:mod:`~merge.core.kabsch`) and
the worker threads (:mod:`~merge.core.parallel`).
"""

from merge.core.errors import MergeCancelled, PatchSetError
from merge.core.patchset import Patch, PatchSet
from merge.core.transforms import PatchTransform

__all__ = ["MergeCancelled", "Patch", "PatchSet", "PatchSetError", "PatchTransform"]
