"""Which pair measurements of the coarse start to believe, and how far.

A correlation peak claims a shift and, through the texture of its overlap, an XY information
matrix (2 x 2: a straight edge fixes only its normal). These rules take back what a peak
cannot know: the direction along its own ridge of alike peaks (:func:`along_ridge_removed`),
a score far below the set's usual (a chance peak, :func:`drop_odd_scores`), directions a
patch's pairs hardly measure all taken together (:func:`drop_unconstrained`); and they name
the patches whose links found nothing or conflict, to be placed against all their neighbours
(:func:`patches_in_doubt`). What no rule can take back, a periodic sample's overlaps that
repeat themselves, they name (:func:`periodic_repeat`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Information along an edge below this fraction of that across it counts as none...
APERTURE = 0.01
#: Alike peaks on a peak's own ridge whose offsets spread across the ridge by more than this
#: fraction (of their second moments) make a plateau: no direction measured.
PLATEAU = 0.1
#: A first-pass peak scoring this many robust spreads below the median of all pairs' peaks is
#: taken for a chance one (see :func:`drop_odd_scores`); the spread is at least SCORE_SPREAD_FLOOR.
ODD_SCORE = 5.0
SCORE_SPREAD_FLOOR = 0.02
#: A pair the network weighs below this is in doubt: measured again, and its patches placed
#: against all their neighbours.
DOUBT = 0.2
#: A link the network weighs at least this much holds its patches.
TRUSTED = 0.5
#: Share of the pairs the start measured whose overlaps repeat themselves at one distance
#: (within :data:`PERIOD_SPREAD` of their median) from which the sample counts as periodic
#: (:func:`periodic_repeat`). Some pairs repeat on any sample, at any distance (bumps along a
#: chessboard's edges: 2 % of a large mosaic's pairs, up to a third of a small one's, 100-330
#: nm apart; a folded surface's folds, up to 1 %); the real 1-D grating's do in 56 % of a
#: 3 x 3 mosaic's pairs and all of a 2 x 2's, 310-350 nm apart.
PERIODIC_SHARE = 1.0 / 3.0
PERIOD_SPREAD = 0.1
#: Pairs that must repeat at one distance, however few the pairs: two of a 2 x 2 TGX1
#: mosaic's four (bumps along its edges, 136 nm apart, variation draw 3065) said it periodic,
#: which spared its start a second opinion (`merge.pipeline`): 15.8 x the floor where the
#: second opinion makes 1.3 x. The real grating's 2 x 2 mosaics repeat in 4-6 of their six.
PERIODIC_LEAST = 3


def patch_information(n: int, pairs: IntArray, W: FloatArray) -> FloatArray:
    """(n, 2, 2) sum of the XY information ``W`` (k, 2, 2) of every patch's pairs."""
    info = np.zeros((n, 2, 2))
    np.add.at(info, pairs[:, 0], W)
    np.add.at(info, pairs[:, 1], W)
    return info


def along_ridge_removed(info: FloatArray, ridge: Sequence[tuple[int, int]]) -> FloatArray:
    """The XY information ``info`` (2 x 2, x then y) of a peak less the direction its
    ``ridge`` offsets ``(dy, dx)`` run along.

    Where a correlation peak has as likely peaks on its own ridge, which of them is the true
    shift is chance, however much texture the overlap shows along it: on the real grating
    (draw 29) a bump 100 nm along the stripes from the true shift claimed a precision of a few
    nanometres across and along them, and its patches merged 98 nm off (map 20.5 x the floor;
    without the claim 2.0 x). The direction is the offsets' principal axis (the far ones weigh
    most); offsets spread over more than :data:`PLATEAU` of it in the other direction make a
    plateau, and nothing is measured.
    """
    out = np.array(info, dtype=np.float64)
    if not len(ridge):
        return out
    d = np.array([(dx, dy) for dy, dx in ridge], dtype=np.float64)
    vals, vecs = np.linalg.eigh(d.T @ d)
    if vals[0] > PLATEAU * vals[1]:
        return np.zeros((2, 2))
    P = np.eye(2) - np.outer(vecs[:, 1], vecs[:, 1])
    projected: FloatArray = P @ out @ P
    return projected


def drop_unconstrained(
    x: FloatArray,
    pairs: IntArray,
    W: FloatArray,
    *,
    texture: FloatArray | None = None,
    least: float = np.inf,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Zero each patch's offset along directions its pairs hardly measure, all taken together;
    and whether they measure both directions.

    The pairs of a patch on a 1-D structure (a grating's stripes, a single straight edge) all
    measure nearly the same direction; their small differences in angle would otherwise turn
    their errors across the edge into large, meaningless offsets along it.

    ``texture`` (k, 2, 2), the part of ``W`` that the texture beside a straight edge measured
    along it (:func:`merge.start.texture.along_edge`): an offset along a direction that it
    measures with ``least`` information or more (a patch's pairs together) is kept, however
    much more its edges measure across. That texture is granted a cell's precision, a
    hundredth of the information a sharp peak claims across its edge: counted against those
    alone, a patch with more edge pairs than textured ones lost the texture's measurement
    along its edges and went back where the stage put it (a TGX1-like mosaic of 45 x 90 px
    patches at 40 % overlaps, variation draw 2110: three patches 66-192 nm off, the map 21 x
    the floor, though every textured pair had measured within 10 nm). Such a patch is still
    not complete: the refinement treats it as one the start did not measure both ways (its
    widest level frees it, from a place now a cell or so off; counted as measured, 15 of the
    grating sweep's 240 runs came out 1-4 % worse, and none better).
    """
    info = patch_information(len(x), pairs, W)
    along = None if texture is None else patch_information(len(x), pairs, texture)
    out = x.copy()
    complete = np.zeros(len(x), dtype=bool)
    for c in range(len(x)):
        vals, vecs = np.linalg.eigh(info[c])
        hardly = vals < APERTURE * max(vals.max(), 0.0)
        complete[c] = vals.max() > 0 and not hardly.any()
        if along is not None:  # what the texture measures along each direction
            hardly &= np.einsum("ij,ik,kj->j", vecs, along[c], vecs) < least
        weak = vecs[:, hardly]
        out[c] -= weak @ (weak.T @ x[c])
    return out, complete


def drop_odd_scores(
    score: FloatArray,
    xy_w: FloatArray,
    *,
    excess: FloatArray | None = None,
    significance: float = np.inf,
) -> None:
    """Unmeasure (in place) first-pass pairs whose peak scores far below the set's usual,
    unless it stands ``significance`` or more above the chance peaks of its own window
    (``excess``, per pair).

    On one surface the true peaks of all pairs score alike (0.95-0.99 on a textured sample); a
    pair whose true shift lies beyond the search window still returns its best peak inside,
    a chance one that scores far lower and would claim the full precision of a real one. Such
    pairs are measured again in the second pass, near the shift their neighbours predict.
    But on a grating the pairs that hold an edge score 0.95 and those that hold only the
    roughness of a face 0.5: such a peak is no chance one where it stands out of its window
    (1 µm patches, 50 nm ramps, draw 3: a corner patch whose one face-only pair, score 0.50 at
    5.5 spreads above chance, was dropped; its other pairs held one edge direction, and it
    merged 125 nm off along the other).
    """
    found = np.isfinite(score)
    if found.sum() < 8:
        return
    med = float(np.median(score[found]))
    spread = max(1.4826 * float(np.median(np.abs(score[found] - med))), SCORE_SPREAD_FLOOR)
    odd = found & (score < med - ODD_SCORE * spread)
    if excess is not None:
        odd &= ~(excess >= significance)
    xy_w[odd] = 0.0


def patches_in_doubt(
    n: int,
    pairs: IntArray,
    unmeasured: NDArray[np.bool_],
    robust: FloatArray,
    can: NDArray[np.bool_],
    W: FloatArray,
) -> list[int]:
    """Patches with measurable pairs of which none is trusted or some conflict with the rest;
    those with the most trusted links first (their neighbours are the likeliest in place).

    Not a patch whose pairs (information ``W``, (k, 2, 2)) measured one direction only: on a
    1-D structure (a grating) where it lies along the stripes is a guess that a pooled search
    would only replace by a bump of the ridge.
    """
    trusted = np.bincount(pairs[~unmeasured & (robust >= TRUSTED)].ravel(), minlength=n)
    conflicting = np.bincount(pairs[can & ~unmeasured & (robust < DOUBT)].ravel(), minlength=n)
    measurable = np.bincount(pairs[can].ravel(), minlength=n)
    doubt = np.flatnonzero((measurable > 0) & ((trusted == 0) | (conflicting > 0)))
    vals = np.linalg.eigvalsh(patch_information(n, pairs, W)[doubt])
    doubt = doubt[(vals[:, 1] == 0) | (vals[:, 0] >= APERTURE * vals[:, 1])]
    order: list[int] = doubt[np.argsort(-trusted[doubt], kind="stable")].tolist()
    return order


def periodic_repeat(repeat: FloatArray, information: FloatArray) -> float:
    """How far (metres) a periodic sample's overlaps repeat themselves, or NaN where the
    sample does not show itself periodic: at least :data:`PERIODIC_SHARE` of the pairs
    measured (``information`` (k, 2, 2) not zero), and :data:`PERIODIC_LEAST`, must hold a
    shift as likely as their own (``repeat`` (k,) metres off, infinite where none:
    :attr:`merge.start.CoarseStart.repeat`) at one distance, within :data:`PERIOD_SPREAD` of
    the median. Which repeat is the true shift no overlap tells: the start takes the one
    nearest where the stage put the pair."""
    measured = np.trace(information, axis1=1, axis2=2) > 0
    found = repeat[measured & np.isfinite(repeat)]
    if not len(found):
        return float("nan")
    middle = float(np.median(found))
    alike = found[np.abs(found - middle) <= PERIOD_SPREAD * middle]
    if len(alike) < max(PERIODIC_LEAST, PERIODIC_SHARE * measured.sum()):
        return float("nan")
    return float(np.median(alike))
