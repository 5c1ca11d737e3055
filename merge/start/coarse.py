"""A robust start: Z offsets and XY shifts of all patches, before any nearest-neighbour search.

In snake order, vertically adjacent patches were scanned up to two rows apart in time, so their Z
offsets can differ by hundreds of nanometres, far more than the grid spacing: a 3-D
nearest-neighbour search would pair the wrong points. So first, for every overlapping pair, a
masked normalized cross-correlation of the down-sampled heights and slopes
(:func:`merge.start.lattice.correlated_channels`)
measures the XY shift — it is blind to Z offsets by construction; of peaks a period apart (a
grating) that score alike, the one nearest the expected shift wins — and the median height
difference at that shift measures the Z offset. All patches are then solved at once from these
pairwise differences (:mod:`merge.start.network`), with robust weights and with each pair's XY
information as a 2 x 2 matrix (a straight edge fixes only its normal). Inside a large mosaic
the corner pairs (patches diagonal to each other) are measured only where the side pairs around
them conflict (:func:`spare_corners`). A patch whose links
found nothing or disagree with the rest is then placed against all its neighbours at once
(:mod:`merge.start.placement`), and a second pass re-measures the doubtful pairs in a narrow window
around the shift the network, so mended, predicts. Scans levelled one by one before export get
the planes their levelling took back first (:mod:`merge.start.tilts`).

The steps, each a function over two small records:
:func:`~merge.start.averaging.averaged_on_lattice` gives the :class:`Lattice` (grids, noise,
texture, the pairs' nominal overlaps); :func:`_first_pass` fills
:class:`~merge.start.measure.Correlations` (a shift and its information per pair,
:mod:`merge.start.measure`); the network solves them; :func:`_place_doubtful` places the patches
in doubt (:mod:`merge.start.trust` names them); :func:`~merge.start.measure.measure` measures
their pairs again; :func:`_z_offsets` levels them all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.start.averaging import Lattice, averaged_on_lattice
from merge.start.hypotheses import distinct, of_correlations
from merge.start.lattice import overlap_z_difference
from merge.start.measure import (
    ALONG_EDGE,
    AMBIGUITY,
    CHANNEL_WEIGHTS,
    MIN_SCORE,
    SHIFT_PRIOR,
    SIGNIFICANCE,
    Correlations,
    accept,
    correlation,
    measure,
)
from merge.start.ncc import pair_maps
from merge.start.network import NetworkSolution, solve_pair_differences
from merge.start.peaks import find_peak
from merge.start.placement import PairMap, place_patch
from merge.start.trust import (
    DOUBT,
    TRUSTED,
    drop_odd_scores,
    drop_unconstrained,
    patches_in_doubt,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A pair whose nominal overlap is under this share of the largest of its patches' is a corner
#: pair (:func:`spare_corners`).
CORNER_SHARE = 0.5
#: Side pairs that put a patch in closed loops enough to spare its corner pairs at first.
LOOP_SIDES = 4
#: Search radius of a patch placed against all its neighbours, in first-pass radii: wider, since
#: a patch whose links all failed may be the one whose stage error exceeded the first search,
#: and the pooled score of all its pairs is far less prone to chance peaks than one pair's.
PLACE_RADIUS = 1.5
#: NCC from which a pair's peak and the repeats as likely as it (within
#: :data:`~merge.start.measure.AMBIGUITY`) are structure, not chance bumps on a faint texture.
REPEAT_SCORE = 0.6


@dataclass(frozen=True)
class CoarseStart:
    """Initial translations (the rotations start at identity).

    translation : (n, 3) metres, ``t`` of ``q = p + t`` per patch.
    xy_measured : (n,) bool, whether any pair measured the patch's XY.
    xy_complete : (n,) bool, whether its pairs measured XY along both axes.
    xy_measurable : (n,) bool, whether any of its pairs could be correlated (both patches
        textured, enough nominal overlap): where this holds and ``xy_measured`` does not, the
        overlaps should have registered and did not.
    tilt : (n, 2) dz/dx, dz/dy of the plane each patch lost when it was levelled on its own
        before export (zero for raw scans, :mod:`merge.start.tilts`); Z in ``translation`` is
        then at the patch's centre.
    pair_information : (k, 2, 2) what each pair's correlation measured of its XY, 1 / m²
        (zero: nothing), as the network weighed it.
    repeat : (k,) metres from each pair's shift to the nearest as likely one a valley
        separates from it, where the overlap repeats itself (:data:`REPEAT_SCORE`); infinite
        elsewhere. The start took the repeat nearest where the stage put the pair.
    alternatives : (m, n, 3) metres, the translations of other placements the pairs allow as
        well, where their votes split or a peak repeats itself (:mod:`merge.start.hypotheses`;
        m = 0 mostly): the refinement from each is judged by its misfit against the one from
        ``translation``.
    """

    translation: FloatArray
    xy_measured: NDArray[np.bool_]
    xy_complete: NDArray[np.bool_]
    tilt: FloatArray
    xy_measurable: NDArray[np.bool_]
    pair_information: FloatArray
    repeat: FloatArray
    alternatives: FloatArray = field(default_factory=lambda: np.zeros((0, 0, 3)))


def coarse_start(
    patches: Sequence[Patch],
    pairs: IntArray,
    *,
    cell: float,
    max_shift: float,
    estimate_xy: bool = True,
) -> CoarseStart:
    """Estimate every patch's XY and Z offset from its overlaps, simultaneously.

    Parameters
    ----------
    patches : sequence of Patch
    pairs : (k, 2) int array
        Patch pairs that can overlap.
    cell : float, keyword-only
        Side of the common lattice the patches are averaged onto, metres.
    max_shift : float, keyword-only
        Largest XY error of a pair relative to nominal that is searched, metres.
    estimate_xy : bool, keyword-only
        False measures Z offsets only, at the nominal overlaps (plain levelling).
    """
    n = len(patches)
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    lat = averaged_on_lattice(patches, pairs, cell=cell, max_shift=max_shift)
    corr = Correlations.empty(len(pairs))
    translation = np.zeros((n, 3))
    complete = np.zeros(n, dtype=bool)
    weighed = np.zeros((len(pairs), 2, 2))
    repeat = np.full(len(pairs), np.inf)
    alternatives = np.zeros((0, n, 3))
    if estimate_xy and len(pairs):
        translation[:, :2], complete, weighed, others = _xy_offsets(lat, corr, max_shift)
        alternatives = np.zeros((len(others), n, 3))
        alternatives[:, :, :2] = others
        for other in alternatives:
            other[:, 2] = _z_offsets(lat, other)
        for i, offsets in corr.repeats.items():
            # a repeat of a clear peak (whether the network kept the pair, its information says)
            if offsets and corr.score[i] >= REPEAT_SCORE:
                repeat[i] = lat.cell * min(float(np.hypot(*d)) for d in offsets)
    translation[:, 2] = _z_offsets(lat, translation)
    measured = np.zeros(n, dtype=bool)
    measured[pairs[np.trace(corr.xy_w, axis1=1, axis2=2) > 0].ravel()] = True
    measurable = np.zeros(n, dtype=bool)
    can = lat.measurable_pairs()
    measurable[pairs[can].ravel()] = True
    return CoarseStart(
        translation=translation,
        xy_measured=measured,
        xy_complete=complete,
        tilt=lat.tilt,
        xy_measurable=measurable,
        pair_information=weighed,
        repeat=repeat,
        alternatives=alternatives,
    )


def _xy_offsets(
    lat: Lattice, corr: Correlations, max_shift: float
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, FloatArray]:
    """Every patch's XY (n, 2), metres, whether its pairs measured both axes, every pair's
    information as the network weighed it (k, 2, 2), and the XY of the placements the pairs
    allow as well (m, n, 2; :mod:`merge.start.hypotheses`): a first pass over the pairs but the
    spared corners (:func:`spare_corners`), the network solved, the spared corners of patches
    whose links found nothing or conflict measured too and the network solved again, the
    patches in doubt placed against all their neighbours, their pairs and the doubtful ones
    measured again, the network solved again."""
    n, pairs = len(lat.grids), lat.pairs
    radius = max_shift / lat.cell
    # every patch's stage error is a priori within about half the searched range
    xy_prior = 1.0 / (0.5 * max_shift) ** 2
    spare = spare_corners(lat)
    _first_pass(lat, corr, radius, np.flatnonzero(~spare))
    drop_odd_scores(corr.score, corr.xy_w, excess=corr.excess, significance=SIGNIFICANCE)
    sol = solve_pair_differences(n, pairs, corr.xy_m, corr.xy_w, prior=xy_prior)
    # the corners of patches whose links found nothing or conflict are the loops that tell
    # which link is wrong: measured after all, and the network solved again
    unmeasured = (np.trace(corr.xy_w, axis1=1, axis2=2) == 0) & ~spare
    can = lat.measurable_pairs()
    doubted = np.zeros(n, dtype=bool)
    doubted[pairs[can & ~spare & (unmeasured | (sol.robust < DOUBT))].ravel()] = True
    late = spare & (doubted[pairs[:, 0]] | doubted[pairs[:, 1]])
    if late.any():
        _first_pass(lat, corr, radius, np.flatnonzero(late))
        spare &= ~late
        drop_odd_scores(corr.score, corr.xy_w, excess=corr.excess, significance=SIGNIFICANCE)
        sol = solve_pair_differences(n, pairs, corr.xy_m, corr.xy_w, prior=xy_prior)
        unmeasured = (np.trace(corr.xy_w, axis1=1, axis2=2) == 0) & ~spare
    mend = partial(
        _second_pass, lat, unmeasured=unmeasured, spare=spare, radius=radius, prior=xy_prior
    )
    # where the first solve's votes split, each other side mended on its own: the second pass
    # re-measures near the placement it predicts (the network's own would re-measure the
    # pairs that measured the other side near its side, and lose what they said)
    branches = []
    for first in of_correlations(corr, pairs, sol, cell=lat.cell, prior=xy_prior):
        branch = corr.branch()
        branch.xy_m[first.pair] = first.measured
        branches.append(
            (branch, mend(branch, first.solution, honoured=first.pair, scale=sol.scale))
        )
    sol = mend(corr, sol)
    x, complete, weighed = _settled(lat, corr, sol)
    lasts = [
        (corr, h.solution) for h in of_correlations(corr, pairs, sol, cell=lat.cell, prior=xy_prior)
    ]
    others = [_settled(lat, c, o)[0] for c, o in lasts + branches]
    kept = distinct(x, others, cell=lat.cell)
    return x, complete, weighed, np.array([others[i] for i in kept]).reshape(-1, n, 2)


def _second_pass(
    lat: Lattice,
    corr: Correlations,
    sol: NetworkSolution,
    *,
    unmeasured: NDArray[np.bool_],
    spare: NDArray[np.bool_],
    radius: float,
    prior: float,
    honoured: int | None = None,
    scale: float | None = None,
) -> NetworkSolution:
    """The network's solution ``sol`` mended: the patches in doubt placed against all their
    neighbours, their pairs and the doubtful ones measured again (``corr``, in place) near the
    shift the placement predicts, and the network solved again (with the pair ``honoured``
    still taken for right, on the residual ``scale``: a hypothesis's branch)."""
    n, pairs = len(lat.grids), lat.pairs
    can = lat.measurable_pairs()
    doubtful = (unmeasured | (np.minimum(sol.robust, 1.0) < DOUBT)) & ~spare
    # the spared corners, not measured, are no links of the placements
    x_start, moved = _place_doubtful(lat, corr, sol, unmeasured | spare, radius, can & ~spare)
    # second pass: doubtful pairs, and those of placed patches, re-measured near the shift the
    # network (mended by the placements) predicts
    redo = np.flatnonzero(doubtful | moved[pairs[:, 0]] | moved[pairs[:, 1]])
    if not len(redo):
        return sol
    for j in redo.tolist():
        checkpoint()
        pred = x_start[pairs[j, 0]] - x_start[pairs[j, 1]]
        e = lat.expected(j)
        centre = (e[0] + pred[1] / lat.cell, e[1] + pred[0] / lat.cell)
        measure(lat, corr, j, centre, 2.0, radius=radius)
    return solve_pair_differences(
        n, pairs, corr.xy_m, corr.xy_w, prior=prior, honoured=honoured, scale=scale
    )


def _settled(
    lat: Lattice, corr: Correlations, sol: NetworkSolution
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """The network's solution ``sol`` less the directions a patch's pairs hardly measure
    (:func:`~merge.start.trust.drop_unconstrained`): XY (n, 2) metres, whether measured both
    ways (n,), and every pair's information as it was weighed (k, 2, 2)."""
    robust = np.minimum(sol.robust, 1.0)  # a pair taken for right weighs as a trusted one
    weighed = corr.xy_w * robust[:, None, None]
    # a direction held by the texture beside edges: a textured pair the network trusts
    held = np.any(corr.xy_w, axis=(1, 2)) * robust  # a dropped odd score holds nothing
    textured = corr.along_w * held[:, None, None]
    least = TRUSTED * ALONG_EDGE / lat.cell**2
    x, complete = drop_unconstrained(sol.x, lat.pairs, weighed, texture=textured, least=least)
    return x, complete, weighed


def spare_corners(lat: Lattice) -> NDArray[np.bool_]:
    """(k,) the corner pairs a first pass may leave out: both patches hold loops enough in
    their side pairs.

    A corner pair (its nominal overlap under :data:`CORNER_SHARE` of its patches' largest:
    patches diagonal to each other) costs a whole correlation map, as a side pair does, for a
    quarter of its information at 25 % overlaps; half the pairs of a large mosaic are such.
    What corners add is loops: a wrong side pair shows where the loops around it do not close.
    A patch with :data:`LOOP_SIDES` side pairs (inside a mosaic) sits in four closed squares
    of them; one with fewer (at a border or a corner of the mosaic, where a wrong pair has no
    loop to show it) keeps its corners. The start measures the spared corners of patches whose
    links conflict after all (:func:`_xy_offsets`)."""
    pairs, overlap = lat.pairs, lat.nominal_overlap
    n = len(lat.grids)
    can = lat.measurable_pairs()
    largest = np.zeros(n)
    np.maximum.at(largest, pairs[:, 0], overlap)
    np.maximum.at(largest, pairs[:, 1], overlap)
    corner = overlap < CORNER_SHARE * np.maximum(largest[pairs[:, 0]], largest[pairs[:, 1]])
    sides = np.bincount(pairs[can & ~corner].ravel(), minlength=n)
    looped = sides >= LOOP_SIDES
    out: NDArray[np.bool_] = can & corner & looped[pairs[:, 0]] & looped[pairs[:, 1]]
    return out


def _first_pass(lat: Lattice, corr: Correlations, radius: float, which: IntArray) -> None:
    """The measurable pairs ``which`` correlated (batched by image shapes through one set of
    FFTs) and each peak within ``radius`` cells of the nominal shift accepted or not."""
    todo = which[lat.measurable_pairs()[which]].tolist()
    for i, ncc, count, zero in pair_maps(lat.channels, lat.pairs, todo, weights=CHANNEL_WEIGHTS):
        checkpoint(1)
        e = lat.expected(i)
        peak = find_peak(
            ncc,
            count,
            zero,
            expected=(float(e[0]), float(e[1])),
            radius=(radius, radius),
            min_overlap=int(lat.least_overlap[i]),
            prior=SHIFT_PRIOR,
            ambiguity=AMBIGUITY,
        )
        accept(lat, corr, i, peak, radius=radius)
        if not corr.xy_w[i].any():  # a copy: the maps are views of their whole batch's
            corr.keep(i, (ncc.copy(), count.copy(), zero))


def _place_doubtful(
    lat: Lattice,
    corr: Correlations,
    sol: NetworkSolution,
    unmeasured: NDArray[np.bool_],
    radius: float,
    can_measure: NDArray[np.bool_],
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The network's XY (n, 2) with the patches whose links found nothing or conflict placed
    against all their neighbours at once, on the pairs ``can_measure`` (k,); and which
    patches moved."""
    n, pairs, cell = len(lat.grids), lat.pairs, lat.cell
    x_start = sol.x.copy()
    moved = np.zeros(n, dtype=bool)
    for c in patches_in_doubt(n, pairs, unmeasured, sol.robust, can_measure, corr.xy_w):
        checkpoint()
        mine = np.flatnonzero(can_measure & np.any(pairs == c, axis=1))
        u = place_patch(
            [_pair_map(lat, corr, i, c, x_start) for i in mine.tolist()],
            centre=(x_start[c, 1] / cell, x_start[c, 0] / cell),
            radius=PLACE_RADIUS * radius,
            prior=SHIFT_PRIOR,
            ambiguity=AMBIGUITY,
            min_score=MIN_SCORE,
        )
        if u is not None:
            x_start[c] = (u[1] * cell, u[0] * cell)
            moved[c] = True
    return x_start, moved


def _pair_map(lat: Lattice, corr: Correlations, i: int, c: int, x: FloatArray) -> PairMap:
    """Pair ``i`` seen from its patch ``c``, the other patch held at ``x`` (metres)."""
    a, b = int(lat.pairs[i, 0]), int(lat.pairs[i, 1])
    ncc, count, zero = correlation(lat, corr, i)
    e = lat.expected(i)
    held = -x[b] if c == a else x[a]  # shift = e + (x_a - x_b) / cell
    return PairMap(
        ncc=ncc,
        count=count,
        zero=zero,
        at_rest=(e[0] + round(held[1] / lat.cell), e[1] + round(held[0] / lat.cell)),
        sign=1 if c == a else -1,
        min_overlap=int(lat.least_overlap[i]),
    )


def _z_offsets(lat: Lattice, translation: FloatArray) -> FloatArray:
    """Every patch's Z offset (n,), metres, from the median height differences of its pairs at
    the XY the network settled on (``translation``; nominal when XY is not estimated)."""
    n, pairs, cell, sigma = len(lat.grids), lat.pairs, lat.cell, lat.sigma
    k = len(pairs)
    z_m, z_w = np.zeros(k), np.zeros(k)
    # pairs that do not overlap nominally (two thirds of a large mosaic's, near neighbours
    # within the search margin) measure nothing
    for i in np.flatnonzero(lat.nominal_overlap > 0).tolist():
        checkpoint()
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        e = lat.expected(i)
        pred = translation[a, :2] - translation[b, :2]
        shift = (round(e[0] + pred[1] / cell), round(e[1] + pred[0] / cell))
        dz, cnt = overlap_z_difference(lat.grids[a].heights, lat.grids[b].heights, shift)
        if cnt >= 16 and np.isfinite(dz):
            # variance of a median of differences of two noisy maps: (π/2) · 2σ² / count
            var = np.pi * (sigma[a] ** 2 + sigma[b] ** 2) / 2.0 / cnt
            z_m[i], z_w[i] = dz, 1.0 / var
    z: FloatArray = solve_pair_differences(n, pairs, z_m, z_w).x[:, 0]
    return z
