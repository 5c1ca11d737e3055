"""Placing one patch against all its neighbours at once, when its pairwise links disagree.

The coarse start measures every overlapping pair on its own. A pair can return a chance peak:
its true shift lies beyond the searched window, or the true overlap is small and some other
shift happens to correlate better (smooth blobs, a few bumps). When such a pair is a patch's
only link, or conflicts with its only other link, the network cannot tell which one is wrong:
both get low robust weights and the patch lands between them, hundreds of nanometres off.

Moving the patch moves all its overlaps together, so every pair's NCC map can be read at the
shift each candidate displacement implies, with the neighbours held where the network put them.
A chance peak of one pair does not line up with the other pairs' maps; the true displacement
scores on all of them. Each pair's NCC ``r`` over ``n`` overlapping cells is turned into Fisher's
``z = atanh(r)`` (variance about ``1 / n``) and pooled with weights ``n``,
``Z = sum(n atanh r) / sqrt(sum n)``: a high chance score on a small overlap then counts for less
than a good score on a large one. Beyond :data:`SATURATION` of the largest pooled overlap in the
window, more cells count no more: displacements are then ranked by the pooled mean ``z`` alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.start.peaks import find_peak

FloatArray = NDArray[np.float64]

#: Pooled overlaps of at least this fraction of the largest in the window are all credible
#: alike: beyond it, more cells do not make a displacement likelier, and a periodic sample's
#: peaks a period apart (with different overlaps) stay alike for the ambiguity rule.
SATURATION = 0.5
#: NCC clipped to this magnitude before Fisher's transform (atanh(1) is infinite).
MAX_NCC = 0.999


@dataclass(frozen=True)
class PairMap:
    """One pair's correlation, seen from the patch being placed.

    ncc, count : (h, w) arrays
        NCC and overlap count of :func:`merge.start.ncc.masked_ncc` for the pair ``(a, b)``.
    zero : (row, column) index of the zero shift in both maps.
    at_rest : (dy, dx) integer shift, cells, of the pair when the patch sits at displacement 0
        and its neighbour where it is.
    sign : +1 if the patch is the pair's first image ``a``, -1 if its second ``b`` (the pair's
        shift grows with ``a``'s displacement and falls with ``b``'s).
    min_overlap : cells the pair must overlap by for its score to count.
    """

    ncc: FloatArray
    count: FloatArray
    zero: tuple[int, int]
    at_rest: tuple[int, int]
    sign: int
    min_overlap: int


def pooled_maps(
    maps: Sequence[PairMap], centre: tuple[int, int], radius: int
) -> tuple[FloatArray, FloatArray]:
    """Fisher-pooled evidence of all pairs for every displacement within ``radius`` cells of
    ``centre`` ``(dy, dx)``.

    Returns
    -------
    num : (2 radius + 1, 2 radius + 1) array
        ``sum(n atanh r)`` over the pairs overlapping by at least their ``min_overlap`` at the
        displacement ``(centre[0] + row - radius, centre[1] + column - radius)``, cells.
    cells : same shape
        ``sum(n)`` over the same pairs.
    """
    if radius < 0:
        raise ValueError("radius must be non-negative")
    u = np.arange(-radius, radius + 1)
    num = np.zeros((u.size, u.size))
    cells = np.zeros((u.size, u.size))
    for m in maps:
        if m.sign not in (1, -1):
            raise ValueError("sign must be +1 or -1")
        rows = m.zero[0] + m.at_rest[0] + m.sign * (centre[0] + u)
        cols = m.zero[1] + m.at_rest[1] + m.sign * (centre[1] + u)
        r_in = (rows >= 0) & (rows < m.ncc.shape[0])
        c_in = (cols >= 0) & (cols < m.ncc.shape[1])
        rr, cc = np.ix_(np.flatnonzero(r_in), np.flatnonzero(c_in))
        r = m.ncc[rows[rr], cols[cc]]
        n = m.count[rows[rr], cols[cc]]
        use = np.isfinite(r) & (n >= m.min_overlap)
        z = np.where(use, np.arctanh(np.clip(np.where(use, r, 0.0), -MAX_NCC, MAX_NCC)) * n, 0.0)
        num[rr, cc] += z
        cells[rr, cc] += np.where(use, n, 0.0)
    return num, cells


def place_patch(
    maps: Sequence[PairMap],
    *,
    centre: tuple[float, float] = (0.0, 0.0),
    radius: float,
    prior: float = 0.0,
    ambiguity: float = 0.0,
    min_score: float = 0.0,
    min_overlap: int = 16,
) -> tuple[int, int] | None:
    """The displacement ``(dy, dx)``, integer cells, that best fits the patch to all its pairs.

    Parameters
    ----------
    maps : sequence of PairMap
        The patch's pairs, each with its neighbour held in place.
    centre : (dy, dx), keyword-only
        The patch's displacement now, cells: the search is centred on it, and of alike peaks
        (a periodic sample's, a period apart) the nearest to it wins.
    radius : float, keyword-only
        Largest distance from ``centre`` searched along each axis, cells.
    prior, ambiguity : float, keyword-only
        As for :func:`merge.start.peaks.find_peak`, in NCC units: the ranking map is ``tanh`` of the
        pooled mean ``z``, scaled down by ``sqrt`` of the pooled overlap where that is less than
        :data:`SATURATION` of the largest in the window.
    min_score : float, keyword-only
        Pooled NCC ``tanh(sum(n atanh r) / sum n)`` the best displacement must reach.
    min_overlap : int, keyword-only
        Cells all pairs together must overlap by.

    Returns None when no displacement qualifies.
    """
    if not np.isfinite(radius) or radius < 0:
        raise ValueError("radius must be a non-negative number of cells")
    R = int(np.ceil(radius))
    mid = (round(centre[0]), round(centre[1]))
    num, cells = pooled_maps(maps, mid, R)
    if cells.max() <= 0:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_z = num / cells
        evidence = np.sqrt(np.minimum(cells / (SATURATION * cells.max()), 1.0))
        rank = np.where(cells > 0, np.tanh(mean_z * evidence), np.nan)
    peak = find_peak(
        rank,
        cells,
        (R - mid[0], R - mid[1]),
        expected=centre,
        radius=(radius, radius),
        min_overlap=min_overlap,
        prior=prior,
        ambiguity=ambiguity,
    )
    if peak is None:
        return None
    dy, dx = peak.integer_shift
    j = (dy - mid[0] + R, dx - mid[1] + R)
    if np.tanh(num[j] / cells[j]) < min_score:
        return None
    return dy, dx
