"""The peak of a normalized cross-correlation map: where two overlapping images agree best.

A map from :mod:`merge.start.ncc` scores every integer shift. The peak is searched within a window
around the expected shift, refined to sub-pixel by a parabola per axis, and judged: how far it
stands above what chance gives in the window, and which other peaks are as likely (a grating
repeats its peak a period apart; a straight edge draws a ridge of near-equal scores along
itself). Among alike peaks the one nearest the expected shift wins, and the peak reports the
alike ones on its own ridge: along them the shift is not measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class CorrelationPeak:
    """Best shift of ``b`` against ``a``: ``b[y + dy, x + dx] ≈ a[y, x]`` (up to offset and gain).

    shift : (dy, dx) sub-pixel shift, pixels.
    integer_shift : (dy, dx) integer shift at the peak.
    score : NCC at the peak, in [-1, 1].
    overlap : number of pixels both images hold at the peak.
    at_border : the peak lies on the border of the search window (a weak result).
    excess : how far the peak stands above the highest score chance gives in the window, in
        robust spreads of the window's scores (see :func:`_excess`; computed when asked for).
    ridge : (dy, dx) integer offsets, from the peak, of the peaks on its own ridge that are as
        likely (see :func:`find_peak`'s ``ambiguity``): along them the shift is not measured,
        whatever texture the overlap shows there. Empty when the peak stands out.
    repeats : (dy, dx) integer offsets, from the peak, of the peaks as likely that a valley
        separates from it: the overlap repeats itself (a periodic sample), and which repeat is
        the true shift the overlap cannot tell. Empty when none is as likely.
    """

    shift: tuple[float, float]
    integer_shift: tuple[int, int]
    score: float
    overlap: int
    at_border: bool
    window: FloatArray = field(repr=False, compare=False)  # the searched scores
    ridge: tuple[tuple[int, int], ...] = ()
    repeats: tuple[tuple[int, int], ...] = ()

    @property
    def excess(self) -> float:
        return _excess(self.score, self.window)


def find_peak(
    ncc: FloatArray,
    count: FloatArray,
    zero: tuple[int, int],
    *,
    expected: tuple[float, float] = (0.0, 0.0),
    radius: tuple[float, float] | None = None,
    min_overlap: int = 16,
    prior: float = 0.0,
    ambiguity: float = 0.0,
) -> CorrelationPeak | None:
    """The NCC peak within ``radius`` (pixels per axis) of the ``expected`` shift ``(dy, dx)``.

    ``ncc``, ``count`` and ``zero`` are one map from :func:`merge.start.ncc.masked_ncc`: scores and
    overlapping pixels per shift (ny, nx), and the index of the zero shift. Only shifts where at
    least ``min_overlap`` pixels overlap count. The sub-pixel shift comes from a parabola
    through the peak and its neighbours along each axis. Returns None when no shift qualifies.

    ``prior`` is subtracted from the score at the edge of the search radius, quadratically
    less closer in: among near-equal peaks (the ridge a straight edge or a grating draws along
    its own direction) the one nearest the expected shift wins.

    ``ambiguity``: separate peaks scoring within this much of the best are taken as equally
    likely — a periodic structure repeats its peak one period apart, and which of them scores
    highest then depends on noise and on what the overlap happens to hold — and the one nearest
    the expected shift wins. So are bumps along one ridge (the NCC of a straight edge or of a
    grating's stripes is high all along it) unless the best stands out of the ridge by as much:
    then it is the texture along the edge, and it wins (see :func:`_alike`).
    """
    ky = np.arange(ncc.shape[0]) - zero[0]
    kx = np.arange(ncc.shape[1]) - zero[1]
    if radius is not None:
        # the search window's bounding box: all that follows is local to it
        rows = np.flatnonzero(np.abs(ky - expected[0]) <= radius[0])
        cols = np.flatnonzero(np.abs(kx - expected[1]) <= radius[1])
        if rows.size == 0 or cols.size == 0:
            return None
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        ncc, count, ky, kx = ncc[box], count[box], ky[box[0]], kx[box[1]]
    ok = np.isfinite(ncc) & (count >= min_overlap)
    if not ok.any():
        return None
    score = np.where(ok, ncc, -np.inf)
    if prior > 0 and radius is not None:
        d2 = ((ky - expected[0]) / max(radius[0], 1e-9))[:, None] ** 2 + (
            (kx - expected[1]) / max(radius[1], 1e-9)
        )[None, :] ** 2
        score = score - prior * d2
    flat_best = np.unravel_index(int(np.argmax(score)), score.shape)
    best = (int(flat_best[0]), int(flat_best[1]))
    ridge: list[tuple[int, int]] = []
    repeats: list[tuple[int, int]] = []
    if ambiguity > 0:
        best, ridge, repeats = _nearest_alike(score, best, ky, kx, expected, ambiguity)
    iy, ix = best
    sub, border = _subpixel(score, ok, best)
    dy, dx = int(ky[iy]), int(kx[ix])
    return CorrelationPeak(
        shift=(dy + sub[0], dx + sub[1]),
        integer_shift=(dy, dx),
        score=float(ncc[iy, ix]),
        overlap=int(count[iy, ix]),
        at_border=border,
        window=ncc[ok],
        ridge=tuple(ridge),
        repeats=tuple(repeats),
    )


def _nearest_alike(
    score: FloatArray,
    best: tuple[int, int],
    ky: IntArray,
    kx: IntArray,
    expected: tuple[float, float],
    ambiguity: float,
) -> tuple[tuple[int, int], list[tuple[int, int]], list[tuple[int, int]]]:
    """Among the local maxima of ``score`` within ``ambiguity`` of its ``best``, the one
    nearest the ``expected`` shift that is as likely (:func:`_alike`); the offsets (dy, dx)
    of the alike peaks on its own ridge, and of those a valley separates from it (repeats).
    ``ky``, ``kx``: the shifts of the rows and columns."""
    iy, ix = best
    top = score[iy, ix]
    local = (score == ndimage.maximum_filter(score, size=3, mode="constant", cval=-np.inf)) & (
        score >= top - ambiguity
    )
    cy, cx = np.nonzero(local)
    ridge: list[tuple[int, int]] = []
    repeats: list[tuple[int, int]] = []
    if len(cy) <= 1:
        return best, ridge, repeats
    dist2 = (ky[cy] - expected[0]) ** 2 + (kx[cx] - expected[1]) ** 2
    for k in np.argsort(dist2, kind="stable").tolist():
        if _alike(score, (iy, ix), (int(cy[k]), int(cx[k])), ambiguity):
            iy, ix = int(cy[k]), int(cx[k])
            break
    # the chosen peak's alike neighbours on its own ridge: no valley between them, and the
    # peak does not rise above the path to them (bumps of noise along a stripe); and those a
    # valley separates from it, where the overlap repeats itself
    for y, x in zip(cy.tolist(), cx.tolist(), strict=True):
        if (y, x) == (iy, ix):
            continue
        separated, level = _between(score, (iy, ix), (y, x), ambiguity)
        if separated:
            repeats.append((y - iy, x - ix))
        elif level:
            ridge.append((y - iy, x - ix))
    return (iy, ix), ridge, repeats


def _subpixel(
    score: FloatArray, ok: NDArray[np.bool_], peak: tuple[int, int]
) -> tuple[list[float], bool]:
    """The sub-pixel offset (dy, dx) of ``peak`` from a parabola through it and its neighbours
    along each axis, and whether it lies at the window's border (no neighbour on some side)."""
    iy, ix = peak
    sub = [0.0, 0.0]
    border = False
    for axis, (i, n_axis) in enumerate(((iy, score.shape[0]), (ix, score.shape[1]))):
        lo = (i - 1, ix) if axis == 0 else (iy, i - 1)
        hi = (i + 1, ix) if axis == 0 else (iy, i + 1)
        if i - 1 < 0 or i + 1 >= n_axis or not (ok[lo] and ok[hi]):
            border = True
            continue
        f0, fm, fp = score[iy, ix], score[lo], score[hi]
        curv = fm - 2 * f0 + fp
        if curv < 0:
            sub[axis] = float(np.clip(0.5 * (fm - fp) / curv, -0.5, 0.5))
    return sub, border


def _excess(score: float, window: FloatArray) -> float:
    """How many robust spreads of the ``window``'s scores ``score`` stands above the highest of
    as many independent chance scores (``sqrt(2 ln m)`` spreads above their median).

    Where the surfaces share no texture, every score is chance: about normal, with a spread of
    one over the square root of the overlap's independent pixels, so the best of ``m`` shifts
    lies near ``sqrt(2 ln m)`` spreads. A true peak on texture as fine as the noise scores low
    (1.5 nm of roughness under 2 nm of noise: ~0.35) but far above that. Median and spread
    are robust, so the true peak and its lobe barely move them.
    """
    med = float(np.median(window))
    spread = 1.4826 * float(np.median(np.abs(window - med)))
    chance = np.sqrt(2.0 * np.log(max(window.size, 2)))
    return float((score - med) / max(spread, 1e-12) - chance)


def _between(
    score: FloatArray, a: tuple[int, int], b: tuple[int, int], margin: float
) -> tuple[bool, bool]:
    """Along the straight path from peak ``a`` to peak ``b`` of ``score``: whether a valley
    deeper than ``margin`` below ``b`` separates them, and whether ``a`` rises above the path's
    lowest score by no more than ``margin`` (does not stand out of it)."""
    steps = max(abs(b[0] - a[0]), abs(b[1] - a[1]), 1) + 1
    # halves rounded up, not to even: the path is then the same wherever the map starts
    rows = np.floor(np.linspace(a[0], b[0], steps) + 0.5).astype(np.intp)
    cols = np.floor(np.linspace(a[1], b[1], steps) + 0.5).astype(np.intp)
    low = float(score[rows, cols].min())
    return bool(low < score[b] - margin), bool(score[a] - low <= margin)


def _alike(score: FloatArray, best: tuple[int, int], other: tuple[int, int], margin: float) -> bool:
    """Whether peak ``other`` of ``score`` is as likely as the ``best``, both within ``margin``.

    Along the straight path between them, a valley deeper than ``margin`` below ``other``
    separates two peaks (a period apart): alike. Without one they lie on one ridge: alike only
    if the best does not rise above the path by more than ``margin`` (bumps of noise along a
    stripe), not when it does (texture pins the shift along an edge).
    """
    separated, level = _between(score, best, other, margin)
    return separated or level
