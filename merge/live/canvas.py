"""The live mosaic's canvas: the render's sums kept, and a patch's share replaced when it moves.

:func:`merge.render.render_mosaic` is a sum over patches (weighted heights, weights) divided
at the end. A live mosaic changes a few patches at a time, so the canvas keeps the sums and,
for each patch, the transform its share was drawn with: moving a patch takes its old share
out and draws the new one, at a cost of its own pixels, not the mosaic's. The lattice is
anchored once (the first patch's corner) and grows, by whole cells, as patches land beyond it,
so a pixel never moves.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform
from merge.render import Mosaic, MosaicGrid, mosaic_bounds, resample_patch

FloatArray = NDArray[np.float64]

#: Cells added beyond a patch that lands outside the canvas, as a fraction of its side (so
#: that a growing mosaic reallocates a few times, not at every patch).
GROWTH = 0.5


class LiveCanvas:
    """Sums of every patch's share on one growing lattice of pitch ``pixel_size`` (metres).

    Parameters
    ----------
    pixel_size : (dx, dy)
        The mosaic's pixel pitch, metres.
    feather : float, keyword-only
        The blending ramp, as for :func:`merge.render.render_mosaic`.
    """

    def __init__(self, pixel_size: tuple[float, float], *, feather: float = 0.15) -> None:
        dx, dy = float(pixel_size[0]), float(pixel_size[1])
        if not (dx > 0 and dy > 0):
            raise ValueError(f"pixel_size must be positive, got {pixel_size}")
        self.dx, self.dy, self.feather = dx, dy, feather
        self.origin: tuple[float, float] | None = None
        self.acc = np.zeros((0, 0))
        self.wsum = np.zeros((0, 0))
        self.coverage = np.zeros((0, 0), dtype=np.int32)
        #: the patch and transform each drawn share was made with, by patch id
        self._drawn: dict[str, tuple[Patch, PatchTransform]] = {}

    @property
    def grid(self) -> MosaicGrid:
        """The lattice as it stands."""
        if self.origin is None:
            raise ValueError("the canvas holds no patch yet")
        ny, nx = self.acc.shape
        return MosaicGrid(self.origin[0], self.origin[1], self.dx, self.dy, nx, ny)

    def draw(self, patch: Patch, transform: PatchTransform) -> None:
        """Put ``patch`` at ``transform``, replacing its share if it was drawn before."""
        self.erase(patch.id)
        self._cover(mosaic_bounds([patch], [transform]))
        self._add(patch, transform, +1)
        self._drawn[patch.id] = (patch, transform)

    def erase(self, patch_id: str) -> None:
        """Take patch ``patch_id``'s share out (nothing if it was never drawn)."""
        drawn = self._drawn.pop(patch_id, None)
        if drawn is not None:
            self._add(*drawn, -1)

    def mosaic(self) -> Mosaic:
        """The mosaic the sums stand for, cut to the patches' extent (NaN where no patch
        covers)."""
        if self.origin is None:
            raise ValueError("the canvas holds no patch yet")
        covered = self.coverage > 0
        rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
        if not len(rows):
            raise ValueError("the canvas holds no patch")
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        with np.errstate(invalid="ignore", divide="ignore"):
            heights = np.where(covered[box], self.acc[box] / self.wsum[box], np.nan)
        return Mosaic(
            heights=heights,
            origin=(self.origin[0] + cols[0] * self.dx, self.origin[1] + rows[0] * self.dy),
            pixel_size=(self.dx, self.dy),
            coverage=self.coverage[box].copy(),
        )

    def _add(self, patch: Patch, transform: PatchTransform, sign: int) -> None:
        hit = resample_patch(patch, transform, self.grid, self.feather)
        if hit is None:
            return
        ii, jj, wz, w = hit
        self.acc[ii, jj] += sign * wz
        self.wsum[ii, jj] += sign * w
        self.coverage[ii, jj] += sign
        if sign < 0:  # no rounding left where nothing covers any more
            empty = self.coverage[ii, jj] == 0
            self.acc[ii[empty], jj[empty]] = 0.0
            self.wsum[ii[empty], jj[empty]] = 0.0

    def _cover(self, bounds: tuple[float, float, float, float]) -> None:
        """Grow the lattice (whole cells, the old ones in place) until it holds ``bounds``."""
        xmin, ymin, xmax, ymax = bounds
        if self.origin is None:
            self.origin = (xmin, ymin)
        x0, y0 = self.origin
        ny, nx = self.acc.shape
        margin_x = GROWTH * (xmax - xmin) / self.dx
        margin_y = GROWTH * (ymax - ymin) / self.dy
        left = _cells_short((x0 - xmin) / self.dx, margin_x)
        below = _cells_short((y0 - ymin) / self.dy, margin_y)
        right = _cells_short((xmax - x0) / self.dx + 1 - nx, margin_x)
        above = _cells_short((ymax - y0) / self.dy + 1 - ny, margin_y)
        if not (left or below or right or above):
            return
        pad = ((below, above), (left, right))
        self.acc = np.pad(self.acc, pad)
        self.wsum = np.pad(self.wsum, pad)
        self.coverage = np.pad(self.coverage, pad)
        self.origin = (x0 - left * self.dx, y0 - below * self.dy)


def _cells_short(reach: float, margin: float) -> int:
    """Cells to add on one side: none if ``reach`` (cells beyond the edge) is not positive,
    else that plus ``margin``, rounded up."""
    return 0 if reach <= 1e-9 else math.ceil(reach + margin)
