"""The rows of one overlap for the heights' last solve (:mod:`merge.refine.heights`): the
points of one patch read in the other at the places the refinement reached.

Every pixel of patch ``a`` that falls inside ``b`` (all four of ``b``'s pixels around it
measured) is one row: its residual, ``a``'s height less ``b``'s read bilinearly, both through
their transforms; the scan line of ``a`` it lies on and the two of ``b`` it is read between;
its XY from either patch's drift-plane centre; and the slope of ``b`` beneath it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.heightfield import Cells
from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform
from merge.refine.lines import MIN_GROUP

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Pixels added around the part of a patch that can lie over another.
GROW = 2


@dataclass(frozen=True)
class PairRows:
    """The points of one patch ``a`` of a pair read in the other, ``b``: ``r`` (m,) the
    residual (metres), ``line`` (m,) the scan line of ``a`` each lies on, ``j`` and ``f`` (m,)
    the line of ``b`` below it and how far towards the next, ``da`` and ``db`` (m, 2) its XY
    from either patch's drift-plane centre (nominal frames, metres), ``slope2`` (m,) the
    squared slope of ``b`` there (None: flat)."""

    r: FloatArray
    line: IntArray
    j: IntArray
    f: FloatArray
    da: FloatArray
    db: FloatArray
    slope2: FloatArray | None = None

    def blurred(self, xy: float) -> FloatArray:
        """(m,) the variance an XY blur of ``xy`` (metres) adds to every row: its slope's."""
        if self.slope2 is None or xy <= 0:
            return np.zeros_like(self.r)
        out: FloatArray = xy**2 * self.slope2
        return out

    def for_statistics(self) -> PairRows:
        """The rows as :func:`merge.refine.line_statistics.line_statistics` reads them: the
        residuals, ``a``'s lines, the fractions and slopes, without ``j``, ``da`` and ``db``
        (the solve's alone): 32 bytes a row instead of 72, held for some thousand lines at
        once (100 patches of 64 x 64 px: their sample had raised the merge's peak from 55 to
        61 bytes per input pixel)."""
        none = np.empty((0, 2))
        return PairRows(self.r, self.line, np.empty(0, np.intp), self.f, none, none, self.slope2)


def pair_rows(a: Patch, b: Patch, T_a: PatchTransform, T_b: PatchTransform) -> PairRows | None:
    """:class:`PairRows` of ``a``'s pixels that fall inside ``b`` (all four of ``b``'s
    pixels around them measured), None if fewer than :data:`merge.refine.lines.MIN_GROUP`
    (what a line's group needs). Both transforms turn about z only (the refinement's)."""
    ha, hb = np.asarray(a.heights), np.asarray(b.heights)
    nya, nxa = ha.shape
    nyb, nxb = hb.shape
    dxa, dya = a.pixel_size
    # b's corners in a's pixels: the window of a that can lie over b
    corners = np.array(
        [
            [
                b.origin[0] + u * (nxb - 1) * b.pixel_size[0],
                b.origin[1] + v * (nyb - 1) * b.pixel_size[1],
            ]
            for u in (0, 1)
            for v in (0, 1)
        ]
    )
    in_a = ((corners @ T_b.R[:2, :2].T + T_b.t[:2]) - T_a.t[:2]) @ T_a.R[:2, :2]
    cols = (in_a[:, 0] - a.origin[0]) / dxa
    rows = (in_a[:, 1] - a.origin[1]) / dya
    c0, c1 = max(0, int(np.floor(cols.min())) - GROW), min(nxa, int(np.ceil(cols.max())) + GROW + 1)
    r0, r1 = max(0, int(np.floor(rows.min())) - GROW), min(nya, int(np.ceil(rows.max())) + GROW + 1)
    if c1 - c0 < 1 or r1 - r0 < 1:
        return None
    yy, xx = np.mgrid[r0:r1, c0:c1]
    line, x = yy.ravel(), xx.ravel()
    pa = np.column_stack([a.origin[0] + x * dxa, a.origin[1] + line * dya])
    q = pa @ T_a.R[:2, :2].T + T_a.t[:2]
    pb = (q - T_b.t[:2]) @ T_b.R[:2, :2]
    u = (pb[:, 0] - b.origin[0]) / b.pixel_size[0]
    v = (pb[:, 1] - b.origin[1]) / b.pixel_size[1]
    cells = Cells.of(hb.shape, v, u)
    zb = cells.values(hb)
    za = ha[line, x]
    ok = cells.inside & np.isfinite(zb) & np.isfinite(za)  # b's four pixels around it measured
    if ok.sum() < MIN_GROUP:
        return None
    # the cell each row lies in: b's line below it and how far towards the next; its slopes
    i0, j0, fu, fv = cells.col[ok], cells.row[ok], cells.fu[ok], cells.fv[ok]
    gx = (hb[j0, i0 + 1] - hb[j0, i0]) * (1 - fv) + (hb[j0 + 1, i0 + 1] - hb[j0 + 1, i0]) * fv
    gy = (hb[j0 + 1, i0] - hb[j0, i0]) * (1 - fu) + (hb[j0 + 1, i0 + 1] - hb[j0, i0 + 1]) * fu
    slope2 = (gx / b.pixel_size[0]) ** 2 + (gy / b.pixel_size[1]) ** 2
    da, db = pa[ok] - T_a.centre, pb[ok] - T_b.centre
    r = (za[ok] + T_a.t[2] + da @ T_a.slope) - (zb[ok] + T_b.t[2] + db @ T_b.slope)
    return PairRows(r, line[ok], j0, fv, da, db, slope2)
