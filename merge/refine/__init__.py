"""The refinement: all patches' transforms at once, Gauss-Newton on the full-resolution heights.

In: the patches, the pairs near each other at the start's places, and the start's
``T_mosaic_patch`` per patch. Out: :class:`RefineResult`, the refined transforms with the
iterations and residuals, and the raw surfaces (:class:`SurfaceBank`) the report reuses.

The schedule (:mod:`~merge.refine.icp`) runs coarse to fine over levels; every iteration
builds one sparse normal system (:mod:`~merge.refine.normal_system`, with the scan lines'
offsets marginalised, :mod:`~merge.refine.lines`) from the surfaces
(:mod:`~merge.refine.bank`), solves it with its priors (:mod:`~merge.refine.solve`) and moves
every patch, its gauge held (:mod:`~merge.refine.state`), level by level until each stops
(:mod:`~merge.refine.level`); a whole mosaic's heights are then solved once more with every
scan line's offset an unknown of its own (:mod:`~merge.refine.heights`), where those offsets
stand out of their means' noise. The scanner's self-calibration
(:mod:`~merge.refine.scanner`) measures the bend every patch shares from a refined merge.
"""

from merge.refine.bank import SurfaceBank
from merge.refine.icp import DEFAULT_LEVELS, RefineResult, refine
from merge.refine.level import Level
from merge.refine.scanner import ScanDistortion, estimate_distortion, undistort

__all__ = [
    "DEFAULT_LEVELS",
    "Level",
    "RefineResult",
    "ScanDistortion",
    "SurfaceBank",
    "estimate_distortion",
    "refine",
    "undistort",
]
