"""The cell the coarse start correlates on: coarse enough to be fast, fine enough for texture."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from merge.core.downsample import grid_downsample
from merge.core.patchset import Patch
from merge.start.lattice import coherence, fill_empty_lines

#: The coarse start correlates patches of at least about this many cells along their shorter
#: side.
COARSE_CELLS = 32
#: Cells of all patches together the coarse start may correlate on: below it, finer cells.
COARSE_BUDGET = 150_000
#: Median structure-tensor coherence of the patches from which a sample is one-dimensional (a
#: grating: 0.99 in every patch; TGX1 0.3-0.8, MoS2 0.2, the folded surface 0.3, roughness
#: 0.03): it keeps the coarser lattice.
ONE_DIMENSIONAL = 0.95


def coarse_cell(patch_set: Iterable[Patch], cell: float) -> float:
    """The cell of the coarse start: the finer of ``cell`` and the finest pixel pitch (so that
    texture along the fine axis of oblong pixels survives) times a whole factor.

    The factor brings the smaller patch side down to about :data:`COARSE_CELLS` cells (the
    start needs about a pixel of precision, not better), or, where the patches hold fewer
    cells than :data:`COARSE_BUDGET` at a smaller one, to that: texture finer than the cell is
    lost to the start. On a grating's flat faces the only texture is a roughness of ~25 nm;
    cut into 1 µm patches of 200 pixels, 32 cells (31 nm) left the overlaps there to chance
    peaks (bench case tgx1-1um: 5 draws of 8 within 1.5 x the floor, 2 of 10 more off by tens
    of nanometres; at 15 nm 8 of 8 and 10 of 10). Not on a
    one-dimensional sample (:data:`ONE_DIMENSIONAL`): along a grating's stripes finer cells
    resolve noise and defects, whose peaks a stripe-width apart are as likely (the real
    grating, 2 draws of 16 off by 10-90 nm at its pixel pitch).
    """
    side = min(min(p.extent) for p in patch_set)
    fine = min(min(p.pixel_size) for p in patch_set)
    base = min(fine, cell)
    coarsest = max(1, round(side / base / COARSE_CELLS))
    cells = sum(p.extent[0] * p.extent[1] for p in patch_set) / base**2
    finest = max(1, math.ceil(math.sqrt(cells / COARSE_BUDGET)))
    if finest < coarsest and not _one_dimensional(patch_set, base * coarsest):
        return base * finest
    return base * coarsest


def _one_dimensional(patch_set: Iterable[Patch], cell: float) -> bool:
    """Whether the patches, averaged onto ``cell``, show one-dimensional structure (stripes)."""
    grids = [
        fill_empty_lines(grid_downsample(p.heights, p.pixel_size, cell=cell, origin=p.origin))
        for p in patch_set
    ]
    return float(np.median([coherence(g.heights) for g in grids])) >= ONE_DIMENSIONAL
