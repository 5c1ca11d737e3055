"""The paper's literal GPA-ICP (``--method paper``), apart from the default stages.

In: the patches, the pairs that can overlap and initial rotations and translations. Out:
:class:`PaperResult`, every patch's rigid transform, anchored to the nominal frame
(:func:`anchor_to_nominal`) as the default method is.

The pieces of section IV: point clouds down-sampled on a grid (:mod:`merge.core.downsample`)
with their shape index (:mod:`~merge.paper.shape_index`), mutual nearest neighbours and
independent sets (:mod:`~merge.paper.correspondences`), the weighted SVD rigid transform
(:mod:`merge.core.kabsch`, shared with the core's transforms) and the loop
(:mod:`~merge.paper.gpa_icp`).
"""

from merge.paper.gauge import anchor_to_nominal, nominal_points
from merge.paper.gpa_icp import PaperResult, paper_gpa_icp

__all__ = [
    "PaperResult",
    "anchor_to_nominal",
    "nominal_points",
    "paper_gpa_icp",
]
