"""The coarse start: every patch's XY and Z offset from its overlaps, before any fine search.

In: the patches and the pairs that can overlap (:mod:`merge.core`). Out:
:class:`CoarseStart`, a translation per patch (and the plane a patch lost when it was
levelled on its own), with which patches' XY its pairs measured along both axes.

The steps (:mod:`~merge.start.coarse`): average every patch onto one lattice
(:mod:`~merge.start.lattice`, :mod:`~merge.start.cell`), restore the tilts of scans levelled
one by one (:mod:`~merge.start.tilts`), correlate every pair (:mod:`~merge.start.ncc`) and
pick its peak (:mod:`~merge.start.peaks`), solve all patches from the pairwise differences
at once (:mod:`~merge.start.network`), place the patches in doubt against all their
neighbours (:mod:`~merge.start.placement`) and measure their pairs again.
"""

from merge.start.cell import coarse_cell
from merge.start.coarse import CoarseStart, coarse_start

__all__ = ["CoarseStart", "coarse_cell", "coarse_start"]
