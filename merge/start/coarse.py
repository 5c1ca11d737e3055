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
information as a 2 x 2 matrix (a straight edge fixes only its normal). A patch whose links
found nothing or disagree with the rest is then placed against all its neighbours at once
(:mod:`merge.start.placement`), and a second pass re-measures the doubtful pairs in a narrow window
around the shift the network, so mended, predicts. Scans levelled one by one before export get
the planes their levelling took back first (:mod:`merge.start.tilts`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.downsample import grid_downsample
from merge.core.noise import estimate_noise
from merge.core.patchset import Patch
from merge.start.lattice import (
    correlated_channels,
    fill_empty_lines,
    overlap_information,
    overlap_z_difference,
    remove_common_plane,
    texture,
)
from merge.start.ncc import masked_ncc, pair_maps
from merge.start.network import solve_pair_differences
from merge.start.peaks import CorrelationPeak, find_peak
from merge.start.placement import PairMap, place_patch
from merge.start.tilts import levelled_one_by_one, patch_tilts, untilted

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: NCC from which a peak counts whatever the rest of its map looks like.
MIN_SCORE = 0.3
#: Below MIN_SCORE, a peak counts if it stands this many robust spreads above the best that
#: chance gives in its search window (:attr:`merge.start.peaks.CorrelationPeak.excess`).
SIGNIFICANCE = 3.0
#: NCC given up at the search radius to break ties toward the expected shift (see find_peak).
SHIFT_PRIOR = 0.05
#: Correlation peaks within this NCC of the best are equally likely (a grating's period apart):
#: the one nearest the expected shift wins.
AMBIGUITY = 0.1
#: Best precision of a correlation peak, cells.
PRECISION = 0.1
#: Information along an edge below this fraction of that across it counts as none...
APERTURE = 0.01
#: ...unless the texture along it (roughness beside a step) carries this many times the slope
#: energy of the noise: a tenth more or less noise than estimated cannot fake it.
TEXTURE = 1.0
#: Alike peaks on a peak's own ridge whose offsets spread across the ridge by more than this
#: fraction (of their second moments) make a plateau: no direction measured.
PLATEAU = 0.1
#: Pairs correlated together through one set of FFTs.
BATCH = 64
#: A first-pass peak scoring this many robust spreads below the median of all pairs' peaks is
#: taken for a chance one (see _drop_odd_scores); the spread is at least SCORE_SPREAD_FLOOR.
ODD_SCORE = 5.0
SCORE_SPREAD_FLOOR = 0.02
#: A pair the network weighs below this is in doubt: measured again, and its patches placed
#: against all their neighbours.
DOUBT = 0.2
#: A link the network weighs at least this much holds its patches.
TRUSTED = 0.5
#: Search radius of a patch placed against all its neighbours, in first-pass radii: wider, since
#: a patch whose links all failed may be the one whose stage error exceeded the first search,
#: and the pooled score of all its pairs is far less prone to chance peaks than one pair's.
PLACE_RADIUS = 1.5
#: Weights of the correlated channels: heights, x slope, y slope.
CHANNEL_WEIGHTS = (0.5, 0.25, 0.25)
#: Pairs overlapping nominally by fewer cells than this along either axis are not correlated.
MIN_OVERLAP_CELLS = 3
#: A correlation peak must keep at least this fraction of the nominal overlap. Low on purpose:
#: with large stage errors on small overlaps the true peak keeps little of it, and excluding
#: it hands the pair to a wrong one; the robust network outvotes small-overlap mistakes.
MIN_OVERLAP_FRACTION = 0.1
#: A patch whose heights, less their own plane, vary less than this many noise sigmas carries
#: no XY texture. Just above 1 (pure noise): a fine roughness at about a pixel's scale raises
#: the noise estimate as much as the texture, so 1.5 nm of it under 2 nm of noise scores only
#: 1.10-1.26 (a gate at 1.2 left the grating's flat face 40-85 nm off at 2 nm noise). What
#: passes here and has nothing to correlate is caught by its peak's significance.
MIN_TEXTURE = 1.05


@dataclass(frozen=True)
class CoarseStart:
    """Initial translations (the rotations start at identity).

    translation : (n, 3) metres, ``t`` of ``q = p + t`` per patch.
    xy_measured : (n,) bool, whether any pair measured the patch's XY.
    xy_complete : (n,) bool, whether its pairs measured XY along both axes.
    tilt : (n, 2) dz/dx, dz/dy of the plane each patch lost when it was levelled on its own
        before export (zero for raw scans, :mod:`merge.start.tilts`); Z in ``translation`` is then
        at the patch's centre.
    """

    translation: FloatArray
    xy_measured: NDArray[np.bool_]
    xy_complete: NDArray[np.bool_]
    tilt: FloatArray


def _patch_information(n: int, pairs: IntArray, W: FloatArray) -> FloatArray:
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


def _drop_unconstrained(
    x: FloatArray, pairs: IntArray, W: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Zero each patch's offset along directions its pairs hardly measure, all taken together;
    and whether they measure both directions.

    The pairs of a patch on a 1-D structure (a grating's stripes, a single straight edge) all
    measure nearly the same direction; their small differences in angle would otherwise turn
    their errors across the edge into large, meaningless offsets along it.
    """
    info = _patch_information(len(x), pairs, W)
    out = x.copy()
    complete = np.zeros(len(x), dtype=bool)
    for c in range(len(x)):
        vals, vecs = np.linalg.eigh(info[c])
        weak = vecs[:, vals < APERTURE * max(vals.max(), 0.0)]
        out[c] -= weak @ (weak.T @ x[c])
        complete[c] = vals.max() > 0 and weak.shape[1] == 0
    return out, complete


def _drop_odd_scores(score: FloatArray, xy_w: FloatArray) -> None:
    """Unmeasure (in place) first-pass pairs whose peak scores far below the set's usual.

    On one surface the true peaks of all pairs score alike (0.95-0.99 on a textured sample); a
    pair whose true shift lies beyond the search window still returns its best peak inside,
    a chance one that scores far lower and would claim the full precision of a real one. Such
    pairs are measured again in the second pass, near the shift their neighbours predict.
    """
    found = np.isfinite(score)
    if found.sum() < 8:
        return
    med = float(np.median(score[found]))
    spread = max(1.4826 * float(np.median(np.abs(score[found] - med))), SCORE_SPREAD_FLOOR)
    odd = found & (score < med - ODD_SCORE * spread)
    xy_w[odd] = 0.0


def _patches_in_doubt(
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
    vals = np.linalg.eigvalsh(_patch_information(n, pairs, W)[doubt])
    doubt = doubt[(vals[:, 1] == 0) | (vals[:, 0] >= APERTURE * vals[:, 1])]
    order: list[int] = doubt[np.argsort(-trusted[doubt], kind="stable")].tolist()
    return order


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
    anchor = (
        min(p.origin[0] - 0.5 * p.pixel_size[0] for p in patches),
        min(p.origin[1] - 0.5 * p.pixel_size[1] for p in patches),
    )
    grids = [
        fill_empty_lines(
            grid_downsample(p.heights, p.pixel_size, cell=cell, origin=p.origin, anchor=anchor)
        )
        for p in patches
    ]
    # lattice index (row, column) of every grid's cell (0, 0)
    offs = [
        (round((g.y[0] - anchor[1]) / cell - 0.5), round((g.x[0] - anchor[0]) / cell - 0.5))
        for g in grids
    ]
    k = len(pairs)
    nominal_overlap = np.zeros(k)
    for i in range(k):
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        ha, wa = grids[a].heights.shape
        hb, wb = grids[b].heights.shape
        oy = min(offs[a][0] + ha, offs[b][0] + hb) - max(offs[a][0], offs[b][0])
        ox = min(offs[a][1] + wa, offs[b][1] + wb) - max(offs[a][1], offs[b][1])
        nominal_overlap[i] = max(oy, 0) * max(ox, 0) if min(ox, oy) >= MIN_OVERLAP_CELLS else 0
    least_overlap = np.maximum(16, (MIN_OVERLAP_FRACTION * nominal_overlap).astype(int))
    # scans levelled one by one before export: the planes that took off, back first
    tilt = np.zeros((n, 2))
    if levelled_one_by_one([p.heights for p in patches]):
        tilt = patch_tilts(
            grids,
            offs,
            pairs,
            nominal_overlap > 0,
            radius=max_shift / cell,
            min_overlap=least_overlap.tolist(),
        )
        grids = [untilted(g, t, p.center) for g, t, p in zip(grids, tilt, patches, strict=True)]
    levelled = remove_common_plane(grids)
    channels = [correlated_channels(lv) for lv in levelled]
    noise = np.array([estimate_noise(g.heights) for g in grids])
    sigma = np.where(np.isfinite(noise) & (noise > 0), noise, 1e-12)
    textured = np.array(
        [texture(lv) > MIN_TEXTURE * s for lv, s in zip(levelled, sigma, strict=True)]
    )
    radius = max_shift / cell
    xy_m, xy_w = np.zeros((k, 2)), np.zeros((k, 2, 2))
    score = np.full(k, np.nan)

    def expected(i: int) -> tuple[int, int]:
        a, b = pairs[i]
        return offs[a][0] - offs[b][0], offs[a][1] - offs[b][1]

    def measurable(i: int) -> bool:
        a, b = pairs[i]
        return bool(nominal_overlap[i] > 0 and textured[a] and textured[b])

    def accept(i: int, peak: CorrelationPeak | None) -> None:
        a, b = pairs[i]
        xy_w[i] = 0.0
        if peak is None or peak.at_border:
            return
        if peak.score < MIN_SCORE and peak.excess < SIGNIFICANCE:
            return
        score[i] = peak.score
        e = expected(i)
        xy_m[i] = [(peak.shift[1] - e[1]) * cell, (peak.shift[0] - e[0]) * cell]
        s_pair = float(np.hypot(sigma[a], sigma[b]) / np.sqrt(2.0))
        info = overlap_information(
            levelled[a],
            levelled[b],
            peak.integer_shift,
            s_pair,
            precision=PRECISION,
            aperture=APERTURE,
            texture=TEXTURE,
        )
        xy_w[i] = along_ridge_removed(info, peak.ridge) / cell**2

    # NCC maps of the first pass, kept for the second pass and the placements
    maps: dict[int, tuple[FloatArray, FloatArray, tuple[int, int]]] = {}

    def correlation(i: int) -> tuple[FloatArray, FloatArray, tuple[int, int]]:
        if i not in maps:
            a, b = pairs[i]
            maps[i] = masked_ncc(channels[a], channels[b], weights=CHANNEL_WEIGHTS)
        return maps[i]

    def measure(i: int, centre: tuple[float, float], rad: float) -> None:
        peak = None
        if measurable(i):
            peak = find_peak(
                *correlation(i),
                expected=centre,
                radius=(rad, rad),
                min_overlap=int(least_overlap[i]),
                prior=SHIFT_PRIOR,
                ambiguity=AMBIGUITY,
            )
        accept(i, peak)

    def pair_map(i: int, c: int, x: FloatArray) -> PairMap:
        """Pair ``i`` seen from its patch ``c``, the other patch held at ``x`` (metres)."""
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        ncc, count, zero = correlation(i)
        e = expected(i)
        held = -x[b] if c == a else x[a]  # shift = e + (x_a - x_b) / cell
        return PairMap(
            ncc=ncc,
            count=count,
            zero=zero,
            at_rest=(e[0] + round(held[1] / cell), e[1] + round(held[0] / cell)),
            sign=1 if c == a else -1,
            min_overlap=int(least_overlap[i]),
        )

    translation = np.zeros((n, 3))
    complete = np.zeros(n, dtype=bool)
    # every patch's stage error is a priori within about half the searched range
    xy_prior = 1.0 / (0.5 * max_shift) ** 2
    if estimate_xy and k:
        # first pass: all measurable pairs, batched by image shapes through one set of FFTs
        todo = [i for i in range(k) if measurable(i)]
        for i, ncc, count, zero in pair_maps(
            channels, pairs, todo, weights=CHANNEL_WEIGHTS, batch=BATCH
        ):
            e = expected(i)
            maps[i] = (ncc, count, zero)
            accept(
                i,
                find_peak(
                    ncc,
                    count,
                    zero,
                    expected=(float(e[0]), float(e[1])),
                    radius=(radius, radius),
                    min_overlap=int(least_overlap[i]),
                    prior=SHIFT_PRIOR,
                    ambiguity=AMBIGUITY,
                ),
            )
        _drop_odd_scores(score, xy_w)
        sol = solve_pair_differences(n, pairs, xy_m, xy_w, prior=xy_prior)
        unmeasured = np.trace(xy_w, axis1=1, axis2=2) == 0
        doubtful = unmeasured | (sol.robust < DOUBT)
        can_measure = np.array([measurable(i) for i in range(k)], dtype=bool)
        # patches whose links found nothing or conflict: placed against all neighbours at once
        x_start = sol.x.copy()
        moved = np.zeros(n, dtype=bool)
        for c in _patches_in_doubt(n, pairs, unmeasured, sol.robust, can_measure, xy_w):
            mine = np.flatnonzero(can_measure & np.any(pairs == c, axis=1))
            u = place_patch(
                [pair_map(i, c, x_start) for i in mine.tolist()],
                centre=(x_start[c, 1] / cell, x_start[c, 0] / cell),
                radius=PLACE_RADIUS * radius,
                prior=SHIFT_PRIOR,
                ambiguity=AMBIGUITY,
                min_score=MIN_SCORE,
            )
            if u is not None:
                x_start[c] = (u[1] * cell, u[0] * cell)
                moved[c] = True
        # second pass: doubtful pairs, and those of placed patches, re-measured near the shift
        # the network (mended by the placements) predicts
        redo = np.flatnonzero(doubtful | moved[pairs[:, 0]] | moved[pairs[:, 1]])
        if len(redo):
            for j in redo.tolist():
                pred = x_start[pairs[j, 0]] - x_start[pairs[j, 1]]
                e = expected(j)
                measure(j, (e[0] + pred[1] / cell, e[1] + pred[0] / cell), 2.0)
            sol = solve_pair_differences(n, pairs, xy_m, xy_w, prior=xy_prior)
        translation[:, :2], complete = _drop_unconstrained(
            sol.x, pairs, xy_w * sol.robust[:, None, None]
        )
    # Z offsets at the XY the network settled on (nominal overlap when XY is not estimated)
    z_m, z_w = np.zeros(k), np.zeros(k)
    for i in range(k):
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        e = expected(i)
        pred = translation[a, :2] - translation[b, :2]
        shift = (round(e[0] + pred[1] / cell), round(e[1] + pred[0] / cell))
        dz, cnt = overlap_z_difference(grids[a].heights, grids[b].heights, shift)
        if nominal_overlap[i] > 0 and cnt >= 16 and np.isfinite(dz):
            # variance of a median of differences of two noisy maps: (π/2) · 2σ² / count
            var = np.pi * (sigma[a] ** 2 + sigma[b] ** 2) / 2.0 / cnt
            z_m[i], z_w[i] = dz, 1.0 / var
    zsol = solve_pair_differences(n, pairs, z_m, z_w)
    translation[:, 2] = zsol.x[:, 0]
    measured = np.zeros(n, dtype=bool)
    measured[pairs[np.trace(xy_w, axis1=1, axis2=2) > 0].ravel()] = True
    return CoarseStart(
        translation=translation, xy_measured=measured, xy_complete=complete, tilt=tilt
    )
