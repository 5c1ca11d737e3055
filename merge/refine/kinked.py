"""Where a level's raw look-ups draw kinks as straight pieces: the cells near a kink of every
patch, and the look-ups in them redrawn by :func:`merge.core.kinks.subcell_2d`.

The spline through a patch's pixels rings at a kink (a tip-drawn edge's foot or top) by an
amount that depends on where the kink falls between the pixels, so two patches of one edge
draw it differently and the difference reads as a shift. In the cells near a kink the look-ups
draw the straight pieces instead and the kink where they meet; elsewhere the spline stands.
The slopes stay the spline's: they steer the steps, the heights decide where the fit settles
(slopes of the same reconstruction, tried, changed nothing on the tip-drawn chessboard and
moved the folded surface's Z).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from merge.core.kinks import WINDOW, kink_cells, kink_threshold, subcell_2d

if TYPE_CHECKING:
    from merge.refine.bank import SurfaceBank

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Ints = NDArray[np.integer[Any]]


class KinkedCells:
    """Every patch's kink threshold and, pixel by pixel, whether the cell it is the lower
    corner of lies near a kink (patches of ``ny`` x ``nx`` pixels, (n,) each)."""

    def __init__(self, ny: Ints, nx: Ints) -> None:
        #: per patch, the robust spread of its second differences (pixel units)
        self.threshold = np.zeros(len(ny))
        #: the first pixel of every patch in :attr:`cell`, and (last) their count
        self.start = np.concatenate([[0], np.cumsum(np.asarray(nx) * np.asarray(ny))]).astype(
            np.intp
        )
        #: pixel by pixel, patch after patch: the cell near a kink
        self.cell = np.zeros(int(self.start[-1]), dtype=bool)

    def add(self, c: int, heights: FloatArray) -> None:
        """Patch ``c``'s threshold and cells from its raw heights (pixel units); a patch
        narrower than a window has none."""
        if min(heights.shape) < WINDOW:
            return
        threshold = kink_threshold(heights)
        self.threshold[c] = threshold
        self.cell[self.start[c] : self.start[c + 1]] = kink_cells(heights, threshold).ravel()

    def redraw(
        self,
        bank: SurfaceBank,
        dst: Ints,
        u: FloatArray,
        v: FloatArray,
        inside: NDArray[np.bool_],
        h: FloatArray,
    ) -> None:
        """Heights ``h`` (m,) of ``bank``'s look-ups at pixel coordinates (``u``, ``v``) of
        patches ``dst``, redrawn where their cell lies near a kink."""
        nx, ny = bank.nx[dst], bank.ny[dst]
        i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        sel = np.flatnonzero(inside & self.cell.take(self.start[dst] + i0 * nx + j0))
        if not len(sel):
            return
        c = np.asarray(dst, dtype=np.intp)[sel]
        i0, j0 = i0[sel], j0[sel]
        out, _ = subcell_2d(_window(bank, c, i0, j0), v[sel] - i0, u[sel] - j0, self.threshold[c])
        use = np.isfinite(out)
        h[sel[use]] = out[use]


def _window(bank: SurfaceBank, c: IntArray, i0: IntArray, j0: IntArray) -> FloatArray:
    """(m, 10, 10) the pixels rows ``i0 - 4 .. i0 + 5`` and columns ``j0 - 4 .. j0 + 5`` of
    ``bank``'s patches ``c`` (:data:`merge.core.kinks.WINDOW`), read from its nodes and
    continued point-symmetrically beyond the border (as the spline is)."""
    offsets = np.arange(WINDOW) - (WINDOW // 2 - 1)
    rows = _reflected(i0[:, None] + offsets, bank.ny[c][:, None])
    cols = _reflected(j0[:, None] + offsets, bank.nx[c][:, None])
    base = bank.origin[c][:, None, None]
    line = (bank.nodes * bank.grid_nx[c])[:, None, None]
    out = np.zeros((len(c), WINDOW, WINDOW))
    for r_at, r_w in rows:
        for c_at, c_w in cols:
            k = base + r_at[:, :, None] * line + bank.nodes * c_at[:, None, :]
            out += (r_w[:, :, None] * c_w[:, None, :]) * bank.height.take(k)
    return out


def _reflected(index: IntArray, n: IntArray) -> tuple[tuple[IntArray, FloatArray], ...]:
    """Pixels ``index`` (m, k) of lines of ``n`` (m, 1) pixels as two weighted pixels within
    the line each: itself (weights 1, 0) inside, the point-symmetric continuation
    ``2 h(edge) - h(mirror)`` outside."""
    last = n - 1
    below, above = index < 0, index > last
    edge = np.where(below, 0, np.where(above, last, index))
    mirror = np.clip(np.where(below, -index, np.where(above, 2 * last - index, index)), 0, last)
    out = ~(below | above)
    return (
        (edge, np.where(out, 1.0, 2.0)),
        (mirror, np.where(out, 0.0, -1.0)),
    )
