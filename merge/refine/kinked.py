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

from merge.core.kinks import (
    DRAWING,
    KINKED,
    RINGS,
    ROW_KINKED,
    WINDOW,
    bicubic,
    kink_cells,
    kink_threshold,
    subcell_2d,
    subcell_2d_rows,
)

if TYPE_CHECKING:
    from merge.refine.bank import SurfaceBank

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Ints = NDArray[np.integer[Any]]


class KinkedCells:
    """Every patch's kink threshold and, pixel by pixel, how the cell it is the lower corner of
    is drawn (patches of ``ny`` x ``nx`` pixels, (n,) each). The codes take a byte a pixel, held
    only once some patch has a kink (a mosaic without any holds none)."""

    def __init__(self, ny: Ints, nx: Ints) -> None:
        #: per patch, the robust spread of its second differences (pixel units)
        self.threshold = np.zeros(len(ny))
        #: the first pixel of every patch in :attr:`cell`, and (last) their count
        self.start = np.concatenate([[0], np.cumsum(np.asarray(nx) * np.asarray(ny))]).astype(
            np.intp
        )
        #: pixel by pixel, patch after patch: how the cell is drawn
        #: (:func:`merge.core.kinks.kink_cells`' codes), or None while no patch has a kink
        self.cell: NDArray[np.uint8] | None = None

    def add(self, c: int, heights: FloatArray) -> None:
        """Patch ``c``'s threshold and cells from its raw heights (pixel units); a patch
        narrower than a window has none."""
        if min(heights.shape) < WINDOW:
            return
        threshold = kink_threshold(heights)
        self.threshold[c] = threshold
        codes = kink_cells(heights, threshold)
        if self.cell is None:
            if not codes.any():
                return
            self.cell = np.zeros(int(self.start[-1]), dtype=np.uint8)
        self.cell[self.start[c] : self.start[c + 1]] = codes.ravel()

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
        if self.cell is None:
            return
        nx, ny = bank.nx[dst], bank.ny[dst]
        i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        code = np.where(inside, self.cell.take(self.start[dst] + i0 * nx + j0) & DRAWING, 0)
        for kind in (RINGS, KINKED):
            sel = np.flatnonzero(code == kind)
            if not len(sel):
                continue
            c = np.asarray(dst, dtype=np.intp)[sel]
            i, j = i0[sel], j0[sel]
            fv, fu = v[sel] - i, u[sel] - j
            if kind == RINGS:
                out = bicubic(_window(bank, c, i, j, size=4), fv, fu)
            else:
                out = self._kinked(self.cell, bank, c, i, j, fv, fu)
            use = np.isfinite(out)
            h[sel[use]] = out[use]

    def _kinked(
        self,
        cell: NDArray[np.uint8],
        bank: SurfaceBank,
        c: IntArray,
        i: IntArray,
        j: IntArray,
        fv: FloatArray,
        fu: FloatArray,
    ) -> FloatArray:
        """:func:`merge.core.kinks.subcell_2d` at cells (``i``, ``j``) of patches ``c``. Where
        the window's rows all lie in the patch their readings are the codes' (made on the same
        pixels), so only 40 pixels and the column are read; elsewhere (rows continued past a
        border) the whole window."""
        before = WINDOW // 2 - 1
        known = (i - before >= 0) & (i + WINDOW - before - 1 <= bank.ny[c] - 1)
        out = np.empty(len(c))
        k = np.flatnonzero(known)
        if len(k):
            rows = i[k, None] + np.arange(WINDOW) - before
            at = self.start[c[k], None] + rows * bank.nx[c[k], None] + j[k, None]
            kinked_rows = (cell.take(at) & ROW_KINKED).astype(bool)
            window = _window(bank, c[k], i[k], j[k], columns=4)
            out[k] = subcell_2d_rows(window, kinked_rows, fv[k], fu[k], self.threshold[c[k]])
        k = np.flatnonzero(~known)
        if len(k):
            window = _window(bank, c[k], i[k], j[k])
            out[k] = subcell_2d(window, fv[k], fu[k], self.threshold[c[k]])[0]
        return out


def _window(
    bank: SurfaceBank,
    c: IntArray,
    i0: IntArray,
    j0: IntArray,
    *,
    size: int = WINDOW,
    columns: int | None = None,
) -> FloatArray:
    """(m, size, columns) the pixels around cells (``i0``, ``j0``) of ``bank``'s patches ``c``
    (rows from ``size / 2 - 1`` before the cell's corner, 10: -4 .. 5,
    :data:`merge.core.kinks.WINDOW`; columns likewise, ``size`` of them unless ``columns``
    says), read from its nodes and continued point-symmetrically beyond the border (as the
    spline is)."""
    width = size if columns is None else columns
    offsets = np.arange(size) - (size // 2 - 1)
    across = np.arange(width) - (width // 2 - 1)
    (r_edge, r_w), (r_mirror, r_wm) = _reflected(i0[:, None] + offsets, bank.ny[c][:, None])
    (c_edge, c_w), (c_mirror, c_wm) = _reflected(j0[:, None] + across, bank.nx[c][:, None])
    base = bank.origin[c][:, None, None]
    line = (bank.nodes * bank.grid_nx[c])[:, None, None]

    out = (r_w[:, :, None] * c_w[:, None, :]) * _read_at(bank, base, line, r_edge, c_edge)
    # the continuation's mirrored pixels, only for the windows that reach past a border
    rows_out = np.flatnonzero((r_wm != 0).any(axis=1))
    if len(rows_out):
        at = rows_out
        out[at] += (r_wm[at, :, None] * c_w[at, None, :]) * _read_at(
            bank, base[at], line[at], r_mirror[at], c_edge[at]
        )
    cols_out = np.flatnonzero((c_wm != 0).any(axis=1))
    if len(cols_out):
        at = cols_out
        out[at] += (r_w[at, :, None] * c_wm[at, None, :]) * _read_at(
            bank, base[at], line[at], r_edge[at], c_mirror[at]
        )
        both = np.flatnonzero((c_wm[at] != 0).any(axis=1) & (r_wm[at] != 0).any(axis=1))
        if len(both):
            at = at[both]
            out[at] += (r_wm[at, :, None] * c_wm[at, None, :]) * _read_at(
                bank, base[at], line[at], r_mirror[at], c_mirror[at]
            )
    return out


def _read_at(
    bank: SurfaceBank, base: IntArray, line: IntArray, rows: IntArray, cols: IntArray
) -> FloatArray:
    """(m, k, k) ``bank``'s pixels (``rows`` x ``cols``) from nodes ``base`` on."""
    k = base + rows[:, :, None] * line + bank.nodes * cols[:, None, :]
    out: FloatArray = bank.height.take(k).astype(np.float64)
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
