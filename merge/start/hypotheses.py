"""Other placements the start's pairs allow, where their votes cannot tell which is right.

The network (:mod:`merge.start.network`) weighs every pair by how well it agrees with the rest
and settles where most pairs agree. Inside a large mosaic a wrong pair is outvoted: the loops
through it (three or four) all disagree with it. In a small one, or across a row of a mosaic
only two or three pairs tie, the votes can split evenly: a corner pair whose peak slid along an
edge and the side pair beside it that says otherwise, each with one other pair on its side.
The iterations then keep whichever side the plain least squares began nearest, and the patches
beyond it land a whole edge's length off while every pair the network kept holds them (TGX1's
small patches, variation draw 5975: two columns 175 nm off; MoS2, draw 5307: a row 60-100 nm
off, every patch of it held). Or no vote is cast at all: of two peaks as likely in a pair's
map (a repeat, :attr:`merge.start.peaks.CorrelationPeak.repeats`) the one nearest where the
stage put the pair is taken, and where the stage erred by more than half their distance and
no other pair ties the patches beyond it, nothing says otherwise (5307 at 15-25 % overlaps: a
row's one link 300 nm off, its repeat 12 nm). The overlaps' misfit after the refinement can
tell such placements apart, where the pairs cannot: from the right one the same data leave
less residual (5975: 1.51 nm RMS against 1.78; 5307: 0.95 against 1.11).

So each pair the network doubts (:data:`~merge.start.trust.DOUBT`), and each repeat of a
pair's peak at the repeat's shift, is taken for right in turn (a :class:`Hypothesis`,
``honoured`` by :func:`~merge.start.network.solve_pair_differences`). If the placement it
leads to is held by at most one pair fewer than the network's own (the votes split), it is an
alternative for the refinement to judge (:func:`merge.opinions.second_opinion`). Where a wrong
pair is outvoted, believing it turns the loops through it into doubters: more votes lost than
that, and nothing is tried.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.start.measure import Correlations
from merge.start.network import NetworkSolution, solve_pair_differences
from merge.start.trust import DOUBT

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Most alternatives offered (each costs the merge a refinement to judge it).
MOST = 3
#: Mosaics of more patches are offered no alternative: many loops tie their blocks, so a lone
#: link or an even split is rare, and each alternative costs a refinement of all of them (on
#: the grating sweep's 5 x 10 paper grids, whose edges' bumps repeat in a few pairs, 1-2
#: alternatives in 5 of 36 runs doubled a merge of under 3 s and changed nothing). The
#: variation draws they mended held 6-18 patches.
LARGEST = 40
#: Patches times hypotheses solved at most (a network solve each; a periodic sample's pairs
#: all repeat): every doubted pair and repeat of a 2 x 2 mosaic, 27 of a 6 x 6.
BUDGET = 1000
#: Pairs a placement may be held by fewer than the network's own and still split the vote.
SPLIT_VOTES = 1
#: Alternatives that move no patch by more than this many cells from the network's placement
#: (or from an alternative already kept) are the same placement.
SAME_CELLS = 1.0
#: Share of the patches an alternative must move (by more than :data:`SAME_CELLS`): a patch
#: put on a wrong match raises its own misfit by a fifth to a half (MoS2 and TGX1 draws), so
#: fewer than a twentieth of the patches cannot change the misfit of the whole mosaic by what
#: told two fits apart (1 % of the residual RMS, before :data:`merge.opinions.EVIDENCE`), and
#: each alternative costs a refinement of all of it (a corner patch of a large mosaic held by
#: two pairs against one).
MOVED_SHARE = 0.05


@dataclass(frozen=True)
class Hypothesis:
    """A pair taken for right: its index, the XY difference (2,) metres it is taken to
    measure (its own, or a repeat's), and the network's solution with it honoured."""

    pair: int
    measured: FloatArray
    solution: NetworkSolution


def split_votes(
    n: int,
    pairs: IntArray,
    measured: FloatArray,
    weights: FloatArray,
    base: NetworkSolution,
    *,
    cell: float,
    prior: float = 0.0,
    repeats: Mapping[int, Sequence[tuple[int, int]]] | None = None,
) -> list[Hypothesis]:
    """The placements the start's pairs allow as well as the network's ``base``.

    Parameters
    ----------
    n : int
        Number of patches.
    pairs, measured, weights :
        As for :func:`~merge.start.network.solve_pair_differences`: (k, 2) patch indices, (k, 2)
        measured XY differences (metres) and (k, 2, 2) their information (1 / m²).
    base : NetworkSolution
        The network's own solution of them.
    cell : float, keyword-only
        The start's cell, metres: placements within :data:`SAME_CELLS` of it are the same.
    prior : float, keyword-only
        As for the network.
    repeats : mapping, keyword-only
        Per pair, the offsets (dy, dx), cells, of the peaks as likely as its own in its map
        (:attr:`merge.start.measure.Correlations.repeats`); default none.

    Returns
    -------
    list of Hypothesis
        Up to :data:`MOST` placements (:func:`distinct` from ``base``), those held by the most
        pairs first, weighed on ``base``'s residual scale. The doubted pairs are tried first,
        the most informative first, then the repeats of measured pairs in the pairs' order:
        :data:`BUDGET` patch-solves at most, and none for a mosaic of more than
        :data:`LARGEST` patches.
    """
    if cell <= 0 or not np.isfinite(cell):
        raise ValueError("cell must be a positive number of metres")
    measured_any = np.trace(weights, axis1=1, axis2=2) > 0
    held = int((measured_any & (base.robust >= DOUBT)).sum())
    doubted = np.flatnonzero(measured_any & (base.robust < DOUBT))
    # the most informative first: a precise measurement the others disagree with
    doubted = doubted[np.argsort(-np.trace(weights[doubted], axis1=1, axis2=2), kind="stable")]
    tries = [(j, measured[j]) for j in doubted.tolist()]
    for j, offsets in sorted((repeats or {}).items()):
        if measured_any[j]:
            tries += [(j, measured[j] + cell * np.array([dx, dy])) for dy, dx in offsets]
    found: list[tuple[int, int, Hypothesis]] = []
    for order, (j, m_j) in enumerate(tries[: BUDGET // max(n, 1) if n <= LARGEST else 0]):
        taken = measured.copy()
        taken[j] = m_j
        sol = solve_pair_differences(
            n, pairs, taken, weights, prior=prior, honoured=j, scale=base.scale
        )
        votes = int((measured_any & (sol.robust >= DOUBT)).sum())
        if votes >= held - SPLIT_VOTES:
            found.append((-votes, order, Hypothesis(j, m_j, sol)))
    found.sort(key=lambda f: (f[0], f[1]))
    kept = distinct(base.x, [f[2].solution.x for f in found], cell=cell)
    return [found[i][2] for i in kept]


def of_correlations(
    corr: Correlations, pairs: IntArray, base: NetworkSolution, *, cell: float, prior: float
) -> list[Hypothesis]:
    """:func:`split_votes` of what the start measured of its ``pairs`` (``corr``: shifts,
    information and the repeats of their peaks)."""
    return split_votes(
        len(base.x), pairs, corr.xy_m, corr.xy_w, base, cell=cell, prior=prior, repeats=corr.repeats
    )


def distinct(base: FloatArray, placements: Sequence[FloatArray], *, cell: float) -> list[int]:
    """Which of ``placements`` (each (n, 2) metres, in order of preference) are others than
    ``base``'s and each other's: up to :data:`MOST`, each moving :data:`MOVED_SHARE` of the
    patches or more from ``base`` by more than :data:`SAME_CELLS` cells (``cell`` metres), and
    some patch that far from every one kept before it."""
    n = len(base)
    least = max(1, int(np.ceil(MOVED_SHARE * n)))
    out: list[int] = []
    for i, x in enumerate(placements):
        if len(out) >= MOST:
            break
        if (_moved(x, base) > SAME_CELLS * cell).sum() < least:
            continue
        if all((_moved(x, placements[o]) > SAME_CELLS * cell).any() for o in out):
            out.append(i)
    return out


def _moved(x: FloatArray, other: FloatArray) -> FloatArray:
    """(n,) distance (metres) each patch lies apart in two placements (n, 2), their median
    offset (the gauge; the median leaves the patches that stayed in place) aside."""
    d = x - other
    d -= np.median(d, axis=0)
    out: FloatArray = np.hypot(d[:, 0], d[:, 1])
    return out
