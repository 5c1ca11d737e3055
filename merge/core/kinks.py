"""Heights between pixels where the surface has kinks: sub-cell reconstruction.

A tip draws a grating's edge as straight flanks that meet the flat faces in kinks (rounded only
by the apex, a fraction of a pixel). A spline through the pixels rings at a kink, over a few
pixels, by a share of the slope's jump times the pixel: at 20 nm pixels and a flank of slope 4,
nanometres. Worse, the ringing depends on where the kink falls between two pixels, which differs
from patch to patch: two patches of one surface are reconstructed differently, and the
difference is read as a shift (the paper grid of 0.6 µm steps at 20 nm pixels, noise-free, from
the true places: 0.73 nm, where look-ups on the true surface leave 0.005-0.06 nm).

Where the second differences along a line of pixels are concentrated on one or two neighbouring
pixels, turning one way, well above the noise and with nothing spilling beyond them, the line is
two straight pieces meeting in a kink. The kink then lies where the line
through the two pixels left of the cell meets the line through the two right of it (Harten's
subcell resolution, for point values): exact on a piecewise-linear surface wherever the kink
falls, so every patch reconstructs the same surface. Elsewhere the pixels are smooth at their
scale and the spline stands. In two dimensions the reconstruction goes along the rows, then
down the column of the row values (a tensor product), which resolves edges along either axis
and at any angle.

Lengths and heights here are in pixels and a height unit (the caller's).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Pixels of the window a cell's reconstruction reads, along each axis: four before the cell,
#: its two corners and four after (the second differences at pixels -3 .. 4, so that a kink on
#: the cell's lines is seen with two second differences beyond it on either side).
WINDOW = 10
#: Second differences below this share of a window's largest count as none (a straight piece):
#: on a tip-drawn flank the kinks' are the slope's jump times the pixel, tens of nanometres.
STRAIGHT = 0.1
#: A kink's turn (its pair of second differences) must exceed this many robust spreads of one
#: (:func:`kink_threshold`: the faces' noise and roughness); below, the two pieces through noisy
#: pixels are no better than the spline. Paper grid, 1 nm noise, seeds 21-23, XY: at 20 spreads
#: the 0.3 µm steps with 25° flanks (turns of 43 nm at 20 nm pixels, some 15 spreads) were
#: left to the spline (0.89 nm); at 12, 0.67 nm, the 0.6 µm steps at 10 nm pixels 0.39 -> 0.34
#: (at 8 no better: 0.66, 0.34), the folded surface, the real MoS2 and the tanh chessboards
#: within 0.003 nm of the spline's.
SIGNIFICANCE = 12.0
#: Share of a kink's turn that the second differences beyond its pair may hold (in absolute
#: value, those one pixel either side and those two, each couple apart), plus two spreads for
#: their noise: a tip's kinks (its apex 5-20 nm at 20 nm pixels) spill under 0.05 of the turn; a
#: crest rounded over a pixel with curved sides (the folded surface's) 0.1-0.2, where two
#: straight pieces draw it worse than the spline does (1D, noise-free: 3.3 nm RMS against 2.1).
SPILL = 0.05
#: Pixels from a kink within which the spline through the pixels still rings by more than a
#: hundredth of a nanometre (its prefilter's influence falls by 2 - √3 ≈ 0.27 a pixel, from
#: some 3 % of the slope's jump times the pixel: 2.4 nm at 20 nm pixels and a slope of 4).
RINGING = 5


def kink_threshold(heights: FloatArray) -> float:
    """The robust spread (1.4826 MAD) of ``heights``' second differences along both axes: on a
    grating mostly the faces' noise and roughness, the unit the kinks are told from it in.

    ``heights`` (ny, nx), any height unit (NaN ignored). Returns 0 where there is nothing to
    measure it on (then any kink that turns at all counts).
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    d = [np.diff(h, 2, axis=axis).ravel() for axis in (0, 1) if h.shape[axis] >= 3]
    if not d:
        return 0.0
    a = np.abs(np.concatenate(d))
    a = a[np.isfinite(a)]
    if not len(a):
        return 0.0
    return 1.4826 * float(np.median(a))


#: :func:`kink_cells`' codes: a cell far from any kink (the spline stands), one within
#: :data:`RINGING` pixels of one whose window holds no kinked line (the local bicubic,
#: :func:`bicubic`, what :func:`subcell_2d` draws there, for 16 pixels instead of 100), and one
#: whose window does (:func:`subcell_2d`).
SPLINE, RINGS, KINKED = 0, 1, 2
#: Bit of :func:`kink_cells`' codes: the row of pixels through the cell's corner is kinked there.
ROW_KINKED = 4
#: The drawing of a cell (:data:`SPLINE`, :data:`RINGS` or :data:`KINKED`) in a code.
DRAWING = 3


def kink_cells(heights: FloatArray, threshold: float) -> NDArray[np.uint8]:
    """(ny, nx) how the cell whose lower corner is each pixel is drawn: :data:`KINKED` where a
    line of :func:`subcell_2d`'s window finds a kink (a row of it, read by :func:`subcell_1d`
    with ``threshold``, the patch's :func:`kink_threshold`; or the column through the cell's
    corners), :data:`RINGS` within :data:`RINGING` pixels of such a line, where the spline
    through the pixels still rings, :data:`SPLINE` elsewhere (and in the last pixel's cell,
    which holds no look-up of its own)."""
    h = np.asarray(heights, dtype=np.float64)
    ny, nx = h.shape
    seen = []  # per axis: the cells whose line along it is kinked
    before = WINDOW // 2 - 1
    for axis in (0, 1):
        found_cells = np.zeros((ny, nx), dtype=bool)
        seen.append(found_cells)
        if h.shape[axis] < 2:
            continue
        lines = np.moveaxis(h, axis, -1)
        padded = np.pad(
            lines, [(0, 0), (before, WINDOW - before - 2)], mode="reflect", reflect_type="odd"
        )
        windows = np.lib.stride_tricks.sliding_window_view(padded, WINDOW, axis=-1)
        flat = windows.reshape(-1, WINDOW)
        # a window turns by at most twice its largest second difference: only those that
        # may reach the significance are read (on most surfaces none)
        bends = np.abs(np.diff(flat, 2, axis=1)).max(axis=1)
        maybe = np.flatnonzero(2.0 * bends > SIGNIFICANCE * threshold)
        kinked = np.zeros(len(flat), dtype=bool)
        if len(maybe):
            part = flat[maybe]
            _, found = subcell_1d(part, np.zeros(len(part)), np.full(len(part), threshold))
            kinked[maybe] = found & np.isfinite(part).all(axis=1)
        full = np.zeros(lines.shape, dtype=bool)
        full[:, :-1] = kinked.reshape(windows.shape[:-1])  # (lines, n - 1)
        found_cells |= np.moveaxis(full, -1, axis)
    along_y, along_x = seen  # lines along axis 0 (columns) first
    near = ndimage.binary_dilation(along_x | along_y, iterations=RINGING, structure=np.ones((3, 3)))
    # the window's rows (i - 4 .. i + 5) at the cell's column, and the columns at its corners
    rows = _shifted_any(along_x, -before, WINDOW - before - 1)
    columns = along_y.copy()
    columns[:, :-1] |= along_y[:, 1:]
    drawing = np.where(rows | columns, KINKED, np.where(near, RINGS, SPLINE))
    out = (drawing | np.where(along_x, ROW_KINKED, 0)).astype(np.uint8)
    out[-1, :] &= np.uint8(ROW_KINKED)
    out[:, -1] &= np.uint8(ROW_KINKED)
    return out


def _shifted_any(mask: BoolArray, lo: int, hi: int) -> BoolArray:
    """(ny, nx) whether ``mask`` holds in rows ``i + lo .. i + hi`` of every cell's column."""
    ny = mask.shape[0]
    out = np.zeros_like(mask)
    for k in range(lo, hi + 1):
        src = mask[max(k, 0) : ny + min(k, 0)]
        out[max(-k, 0) : ny + min(-k, 0)] |= src
    return out


def bicubic(window: FloatArray, fv: FloatArray, fu: FloatArray) -> FloatArray:
    """Lagrange's bicubic through 4 x 4 pixels (m, 4, 4: rows and columns -1 .. 2 around the
    cell [0, 1]²) at (``fv``, ``fu``) (m,): local and exact on a plane or a straight piece; the
    cubic along every row, then down the column (as :func:`subcell_2d` draws lines without a
    kink)."""
    w = np.asarray(window, dtype=np.float64)
    m = len(w)
    rows = _cubic(w.reshape(-1, 4), np.repeat(np.asarray(fu, dtype=np.float64), 4))
    return _cubic(rows.reshape(m, 4), np.asarray(fv, dtype=np.float64))


def subcell_1d(
    values: FloatArray, t: FloatArray, threshold: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Heights at fraction ``t`` of the cell between the fifth and sixth of ten pixels.

    Parameters
    ----------
    values : (m, 10) array
        Heights at pixels -4 .. 5 along the line; the cell is [0, 1].
    t : (m,) array
        Where in the cell, 0 to 1.
    threshold : (m,) array
        :func:`kink_threshold` of each line's patch.

    Returns
    -------
    heights : (m,) array
        Where the line is straight pieces meeting in kinks (``kinked``: its second differences
        come alone or in same-signed pairs with none between, the largest pair turns by
        :data:`SIGNIFICANCE` spreads or more and spills at most :data:`SPILL` of that beyond
        itself), the piece's height:
        in a cell that holds a kink, the piece through pixels -1 and 0 left of it and through 1
        and 2 right of it, the kink where they meet; in any other cell the straight line
        through its corners. Elsewhere (smooth, or a step drawn within a pixel or two, which
        turns the line both ways at once) the cubic through pixels -1 .. 2.
    kinked : (m,) bool array
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != WINDOW:
        raise ValueError(f"values must be (m, {WINDOW}), got shape {v.shape}")
    t = np.asarray(t, dtype=np.float64)
    spread = np.broadcast_to(np.asarray(threshold, dtype=np.float64), (len(v),))
    out = _cubic(v[:, 3:7], t)
    kinked = np.zeros(len(v), dtype=bool)
    d = v[:, :-2] - 2.0 * v[:, 1:-1] + v[:, 2:]  # at pixels -3 .. 4
    a = np.abs(d)
    top = a.max(axis=1)
    # a turn is at most twice the largest second difference: only those lines are read
    maybe = np.flatnonzero(2.0 * top > SIGNIFICANCE * spread)
    if not len(maybe):
        return out, kinked
    v, d, a, t, spread = v[maybe], d[maybe], a[maybe], t[maybe], spread[maybe]
    bent = a >= STRAIGHT * top[maybe, None]
    # straight pieces and kinks: no three bent in a row, no bent pair turning both ways
    both = bent[:, :-1] & bent[:, 1:]
    three = (both[:, :-1] & bent[:, 2:]).any(axis=1)
    turning = (both & (d[:, :-1] * d[:, 1:] < 0)).any(axis=1)
    # the window's kink: its largest pair; sharp, its turn sits on that pair alone (rounded, or
    # between curved pieces, it spills onto the second differences either side)
    pairs = d[:, :-1] + d[:, 1:]
    k = np.argmax(np.abs(pairs), axis=1)[:, None]
    last = d.shape[1] - 1
    # on the cell's lines (pixels -1 .. 2), and measured two pixels either side: nearer the
    # window's end a turn's other side is out of sight (the foot of a step drawn in two or three
    # pixels looks like a kink there, its top's turn beginning just beyond)
    interior = ((k >= 2) & (k + 3 <= last))[:, 0]
    k = np.clip(k, 2, last - 3)
    turn = np.abs(np.take_along_axis(pairs, k, axis=1))[:, 0]
    near = np.take_along_axis(a, k + np.array([-2, -1, 2, 3]), axis=1)
    # beside <= (SPILL + its noise's mean / turn) * turn, without dividing by a zero turn
    limit = SPILL * turn + 2.0 * spread
    sharp = (near[:, 1] + near[:, 2] <= limit) & (near[:, 0] + near[:, 3] <= limit)
    found = (turn > SIGNIFICANCE * spread) & interior & ~three & ~turning & sharp
    kinked[maybe] = found
    if not found.any():
        return out, kinked
    on = np.flatnonzero(found)
    out[maybe[on]] = _pieces(v[on, 3:7], t[on])
    return out, kinked


def _cubic(v: FloatArray, t: FloatArray) -> FloatArray:
    """Lagrange's cubic through pixels -1 .. 2 (``v`` (m, 4)) at ``t`` (m,) in [0, 1]: exact
    for cubics, local (no ringing from afar)."""
    out: FloatArray = (
        -t * (t - 1.0) * (t - 2.0) / 6.0 * v[:, 0]
        + (t + 1.0) * (t - 1.0) * (t - 2.0) / 2.0 * v[:, 1]
        - (t + 1.0) * t * (t - 2.0) / 2.0 * v[:, 2]
        + (t + 1.0) * t * (t - 1.0) / 6.0 * v[:, 3]
    )
    return out


def _pieces(v: FloatArray, t: FloatArray) -> FloatArray:
    """Two straight pieces through pixels -1, 0 and 1, 2 (``v`` (m, 4)) at ``t`` (m,), the kink
    where they meet; the straight line through 0 and 1 where they meet outside [0, 1] (the
    kink lies beyond the cell, one piece covers it) or are parallel."""
    left, right = v[:, 1], v[:, 2]
    s_left, s_right = left - v[:, 0], v[:, 3] - right
    with np.errstate(divide="ignore", invalid="ignore"):
        at = (right - s_right - left) / (s_left - s_right)
    two = np.where(t < at, left + s_left * t, right + s_right * (t - 1.0))
    inside = np.isfinite(at) & (at >= 0.0) & (at <= 1.0)
    out: FloatArray = np.where(inside, two, left + t * (right - left))
    return out


def subcell_2d_rows(
    rows: FloatArray, kinked_rows: BoolArray, fv: FloatArray, fu: FloatArray, threshold: FloatArray
) -> FloatArray:
    """:func:`subcell_2d` where every row's reading is known: ``rows`` (m, 10, 4) the window's
    rows at columns -1 .. 2, ``kinked_rows`` (m, 10) whether :func:`subcell_1d` finds each row
    (its whole window) kinked. Each row is then its two pieces or its cubic at ``fu``, as
    :func:`subcell_1d` draws it, and only the column is read: the same heights from 40 pixels
    instead of 100 and one line's reading instead of eleven."""
    r = np.asarray(rows, dtype=np.float64)
    m = len(r)
    if r.shape != (m, WINDOW, 4):
        raise ValueError(f"rows must be (m, {WINDOW}, 4), got shape {r.shape}")
    flat = r.reshape(-1, 4)
    t = np.repeat(np.asarray(fu, dtype=np.float64), WINDOW)
    column = _cubic(flat, t)
    kinked = np.asarray(kinked_rows, dtype=bool).ravel()
    if kinked.any():
        column[kinked] = _pieces(flat[kinked], t[kinked])
    out, _ = subcell_1d(column.reshape(m, WINDOW), fv, threshold)
    return out


def subcell_2d(
    window: FloatArray, fv: FloatArray, fu: FloatArray, threshold: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Heights at (``fv``, ``fu``) within the centre cell of 10 x 10 windows of pixels.

    ``window`` (m, 10, 10): rows -4 .. 5 and columns -4 .. 5 around the cell [0, 1]²; ``fv``,
    ``fu`` (m,) where in it; ``threshold`` (m,) as in :func:`subcell_1d`. Along every row of
    the window first, then down the column of those values: a line that is not kinked takes
    the local cubic, exact on a straight piece, where a spline would still ring from a kink a few
    pixels away. Returns the heights and whether any of the eleven lines was kinked.
    """
    w = np.asarray(window, dtype=np.float64)
    m = len(w)
    if w.shape != (m, WINDOW, WINDOW):
        raise ValueError(f"window must be (m, {WINDOW}, {WINDOW}), got shape {w.shape}")
    rows, kinked_rows = subcell_1d(
        w.reshape(m * WINDOW, WINDOW), np.repeat(fu, WINDOW), np.repeat(threshold, WINDOW)
    )
    out, kinked = subcell_1d(rows.reshape(m, WINDOW), fv, threshold)
    return out, kinked | kinked_rows.reshape(m, WINDOW).any(axis=1)
