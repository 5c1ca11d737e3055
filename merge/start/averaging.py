"""The coarse start's first step: every patch averaged onto one lattice, ready to correlate.

All patches are averaged onto one lattice of side ``cell`` anchored at the mosaic's corner, so
a pair's nominal shift is a whole number of cells; the planes of scans levelled one by one
before export are restored (:mod:`merge.start.tilts`); each patch's noise and texture decide
whether its pairs can be correlated at all. :class:`Lattice` is what the later steps of
:func:`merge.start.coarse_start` read.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.downsample import GridSample, grid_downsample
from merge.core.noise import estimate_noise
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.start.lattice import correlated_channels, fill_empty_lines, remove_common_plane, texture
from merge.start.tilts import levelled_one_by_one, patch_tilts, untilted

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Pairs overlapping nominally by fewer cells than this along either axis are not correlated.
MIN_OVERLAP_CELLS = 3
#: A correlation peak must keep at least this fraction of the nominal overlap. Low on purpose:
#: with large stage errors on small overlaps the true peak keeps little of it, and excluding
#: it hands the pair to a wrong one; the robust network outvotes small-overlap mistakes.
MIN_OVERLAP_FRACTION = 0.1
#: A patch whose heights, less their own plane, vary less than this many noise sigmas carries
#: no XY texture. Just above 1 (pure noise): a fine roughness at about a pixel's scale raises
#: the noise estimate as much as the texture, so 1.5 nm of it under 2 nm of noise scores only
#: 1.10-1.26 (a gate at 1.2 left the grating's flat face 40-85 nm off at 2 nm noise). What
#: passes here and has nothing to correlate is caught by its peak's significance.
MIN_TEXTURE = 1.05
#: Smoothing of the correlated slopes (:func:`merge.start.lattice.correlated_channels`), in
#: pixels of each axis's finest pitch (at most a cell, :func:`slope_smoothing`). On a lattice
#: of one cell per pixel (most of the benches' mosaics) that is the cell of smoothing the start
#: was tuned with; the variations' real grating (cells of three) moved within its noise (40
#: draws: medians within 0.06 nm, the bench's draws within 0.01 at the median); MoS2's oblong
#: pixels keep a cell across the lines, where a pixel is a cell (176 draws of four blocks: four
#: draws 1.4-2.5 -> 1.0-1.3 x the floor, one of them 7 silent patches -> none, none worse; half
#: a cell there had made them so). Where a cell holds several pixels (more than
#: :data:`~merge.start.cell.COARSE_CELLS` pixels a side on a mosaic too large for the budget to
#: refine the lattice, :func:`merge.start.cell.coarse_cell`; oblong pixels) the cell's averaging
#: has smoothed already, and a cell more took a fine texture out of the slopes: on 20 x 20
#: patches of 64 x 64 px of a sample whose folds lie microns apart (most overlaps a plane with
#: 1 nm of roughness 20 nm across, on cells of two pixels, 31 nm) the start's pairs were 57 nm
#: off at the median and 148 nm at the 90th percentile, the start's XY 276 nm, and the
#: refinement took 27 iterations to end 3.1 nm off; with a pixel of smoothing 13 and 33 nm,
#: 24 nm, 16 iterations and 1.24 nm. Less than a pixel does not hold on a grating's small noisy
#: patches (a 4 x 2 TGX1 draw with 1.85 nm of noise placed two patches 100 nm off in x at half
#: a pixel, and at 0.8).
SLOPE_SMOOTH_PIXELS = 1.0


def slope_smoothing(patches: Sequence[Patch], cell: float) -> tuple[float, float]:
    """The correlated slopes' smoothing (cells; rows, columns): :data:`SLOPE_SMOOTH_PIXELS` of
    each axis's own finest pitch, at most a cell. Along an axis of coarse pixels (oblong ones:
    a cell a pixel) a pixel of the other axis's pitch is half a cell or less, which left the
    slopes across the lines a pixel's noise: a 3 x 4 MoS2 draw (7.8 x 15.5 nm pixels, 1.8 nm of
    noise) placed a row of patches 100 nm off along y, held and silent."""
    pitch_x = min(p.pixel_size[0] for p in patches)
    pitch_y = min(p.pixel_size[1] for p in patches)
    return (
        min(1.0, SLOPE_SMOOTH_PIXELS * pitch_y / cell),
        min(1.0, SLOPE_SMOOTH_PIXELS * pitch_x / cell),
    )


@dataclass(frozen=True)
class Lattice:
    """What the start knows once every patch is averaged onto one lattice of side ``cell``.

    grids : per patch, its heights on the lattice (tilts restored, empty lines filled).
    offs : per patch, the lattice index (row, column) of its grid's cell (0, 0).
    nominal_overlap : (k,) cells each pair overlaps nominally (0: too little to correlate).
    least_overlap : (k,) cells a correlation peak of each pair must keep.
    tilt : (n, 2) the planes of scans levelled one by one (zero for raw scans).
    levelled, channels : per patch, heights less the common plane, and the correlated
        channels (heights and slopes) of those.
    sigma : (n,) noise per patch, metres; textured : (n,) whether it has XY texture.
    """

    cell: float
    pairs: IntArray
    grids: list[GridSample]
    offs: list[tuple[int, int]]
    nominal_overlap: FloatArray
    least_overlap: IntArray
    tilt: FloatArray
    levelled: list[FloatArray]
    channels: list[FloatArray]
    sigma: FloatArray
    textured: NDArray[np.bool_]

    def expected(self, i: int) -> tuple[int, int]:
        """Pair ``i``'s nominal shift ``(dy, dx)``, cells."""
        a, b = self.pairs[i]
        return self.offs[a][0] - self.offs[b][0], self.offs[a][1] - self.offs[b][1]

    def measurable(self, i: int) -> bool:
        """Whether pair ``i`` overlaps enough, and both its patches have texture."""
        a, b = self.pairs[i]
        return bool(self.nominal_overlap[i] > 0 and self.textured[a] and self.textured[b])

    def measurable_pairs(self) -> NDArray[np.bool_]:
        """(k,) :meth:`measurable` of every pair."""
        out: NDArray[np.bool_] = (
            (self.nominal_overlap > 0)
            & self.textured[self.pairs[:, 0]]
            & self.textured[self.pairs[:, 1]]
        )
        return out


def averaged_on_lattice(
    patches: Sequence[Patch], pairs: IntArray, *, cell: float, max_shift: float
) -> Lattice:
    """Every patch averaged onto one lattice of side ``cell`` (metres), the planes of scans
    levelled one by one restored, with its noise, texture and correlated channels."""
    n = len(patches)
    anchor = (
        min(p.origin[0] - 0.5 * p.pixel_size[0] for p in patches),
        min(p.origin[1] - 0.5 * p.pixel_size[1] for p in patches),
    )
    grids = []
    for p in patches:
        checkpoint(1)
        grids.append(
            fill_empty_lines(
                grid_downsample(p.heights, p.pixel_size, cell=cell, origin=p.origin, anchor=anchor)
            )
        )
    # lattice index (row, column) of every grid's cell (0, 0)
    offs = [
        (round((g.y[0] - anchor[1]) / cell - 0.5), round((g.x[0] - anchor[0]) / cell - 0.5))
        for g in grids
    ]
    nominal_overlap = _nominal_overlaps(grids, offs, pairs)
    least_overlap = np.maximum(16, (MIN_OVERLAP_FRACTION * nominal_overlap).astype(int))
    # scans levelled one by one before export: the planes that took off, back first
    tilt = np.zeros((n, 2))
    if levelled_one_by_one([p.heights for p in patches]):
        tilt = patch_tilts(
            grids,
            offs,
            pairs,
            nominal_overlap > 0,
            radius=max_shift / cell,
            min_overlap=least_overlap.tolist(),
        )
        grids = [untilted(g, t, p.center) for g, t, p in zip(grids, tilt, patches, strict=True)]
    levelled = remove_common_plane(grids)
    noise = np.empty(n)
    for c, g in enumerate(grids):
        checkpoint()  # 10,000 patches take seconds
        noise[c] = estimate_noise(g.heights)
    sigma = np.where(np.isfinite(noise) & (noise > 0), noise, 1e-12)
    textured = np.empty(n, dtype=bool)
    channels = []
    smooth = slope_smoothing(patches, cell)
    for c, lv in enumerate(levelled):
        checkpoint()
        textured[c] = texture(lv) > MIN_TEXTURE * sigma[c]
        channels.append(correlated_channels(lv, smooth=smooth))
    return Lattice(
        cell,
        pairs,
        grids,
        offs,
        nominal_overlap,
        least_overlap,
        tilt,
        levelled,
        channels,
        sigma,
        textured,
    )


def _nominal_overlaps(
    grids: Sequence[GridSample], offs: Sequence[tuple[int, int]], pairs: IntArray
) -> FloatArray:
    """(k,) cells every pair overlaps nominally; 0 where fewer than :data:`MIN_OVERLAP_CELLS`
    along either axis."""
    out = np.zeros(len(pairs))
    for i in range(len(pairs)):
        checkpoint()
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        ha, wa = grids[a].heights.shape
        hb, wb = grids[b].heights.shape
        oy = min(offs[a][0] + ha, offs[b][0] + hb) - max(offs[a][0], offs[b][0])
        ox = min(offs[a][1] + wa, offs[b][1] + wb) - max(offs[a][1], offs[b][1])
        out[i] = max(oy, 0) * max(ox, 0) if min(ox, oy) >= MIN_OVERLAP_CELLS else 0
    return out
