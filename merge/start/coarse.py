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

The steps, each a function over two small records:
:func:`~merge.start.averaging.averaged_on_lattice` gives the :class:`Lattice` (grids, noise,
texture, the pairs' nominal overlaps); :func:`_first_pass` fills :class:`Correlations` (a shift and
its information per pair); the network solves them; :func:`_place_doubtful` places the patches in
doubt (:mod:`merge.start.trust` names them); :func:`_measure` measures their pairs again;
:func:`_z_offsets` levels them all.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.start.averaging import Lattice, averaged_on_lattice
from merge.start.lattice import overlap_measurement, overlap_z_difference
from merge.start.ncc import masked_ncc, pair_maps
from merge.start.network import NetworkSolution, solve_pair_differences
from merge.start.peaks import CorrelationPeak, find_peak
from merge.start.placement import PairMap, place_patch
from merge.start.texture import along_edge, texture_image
from merge.start.trust import (
    APERTURE,
    DOUBT,
    along_ridge_removed,
    drop_odd_scores,
    drop_unconstrained,
    patches_in_doubt,
)

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
#: Information along an edge below APERTURE of that across it counts as none, unless the
#: texture along it (roughness beside a step) carries this many times the slope energy of the
#: noise: a tenth more or less noise than estimated cannot fake it.
TEXTURE = 1.0
#: Information (per cell²) along a straight edge that the texture beside it located
#: (:mod:`merge.start.texture`): a precision of a cell, as the least the texture rule above
#: grants (the start needs no better; the refinement measures it on the raw heights).
ALONG_EDGE = APERTURE / PRECISION**2
#: Textures of patches kept for the pairs that follow (a patch's pairs come one after the
#: other; a few megabytes).
TEXTURES = 64
#: Search radius of a patch placed against all its neighbours, in first-pass radii: wider, since
#: a patch whose links all failed may be the one whose stage error exceeded the first search,
#: and the pooled score of all its pairs is far less prone to chance peaks than one pair's.
PLACE_RADIUS = 1.5
#: Bytes of NCC maps the first pass keeps for the second pass and the placements; past it they
#: are computed again when asked for (few are: the pairs in doubt). Kept all, a map of every
#: pair took 60 bytes per input pixel of a mosaic of 64 x 64 px patches, 2.4 GB at 10,000; the
#: first pass keeps only those of pairs it could not accept (the likely doubtful ones).
MAP_CACHE_BYTES = 64 << 20
#: Weights of the correlated channels: heights, x slope, y slope.
CHANNEL_WEIGHTS = (0.5, 0.25, 0.25)


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
    """

    translation: FloatArray
    xy_measured: NDArray[np.bool_]
    xy_complete: NDArray[np.bool_]
    tilt: FloatArray
    xy_measurable: NDArray[np.bool_]
    pair_information: FloatArray


@dataclass
class Correlations:
    """What correlating the pairs has measured so far.

    xy_m : (k, 2) each pair's XY shift off nominal, metres (x, y).
    xy_w : (k, 2, 2) its information, 1 / m² (zero: not measured).
    score : (k,) its peak's NCC (NaN: none accepted).
    excess : (k,) how far that peak stands above the best chance gives in its window
        (:attr:`merge.start.peaks.CorrelationPeak.excess`; NaN: none accepted).
    maps : the NCC maps computed, by pair (the second pass and the placements reuse them).
    ridges : per pair, the offsets (dy, dx) of the peaks the first pass found as likely as its
        own on its ridge (:attr:`merge.start.peaks.CorrelationPeak.ridge`), if any.
    """

    xy_m: FloatArray
    xy_w: FloatArray
    score: FloatArray
    excess: FloatArray
    maps: dict[int, tuple[FloatArray, FloatArray, tuple[int, int]]]
    #: bytes the maps hold (:data:`MAP_CACHE_BYTES` at most)
    held: int = 0
    ridges: dict[int, tuple[tuple[int, int], ...]] = field(default_factory=dict)
    #: the textures of the patches last asked for (:func:`merge.start.texture.texture_image`),
    #: by patch, :data:`TEXTURES` at most: a patch's pairs come one after the other
    textures: dict[int, FloatArray | None] = field(default_factory=dict)

    def texture(self, lat: Lattice, c: int) -> FloatArray | None:
        """Patch ``c``'s texture (None: not a roughness), computed once while it is among the
        last asked for."""
        if c not in self.textures:
            if len(self.textures) >= TEXTURES:
                del self.textures[next(iter(self.textures))]  # the oldest
            self.textures[c] = texture_image(lat.levelled[c])
        return self.textures[c]

    @classmethod
    def empty(cls, k: int) -> Correlations:
        """Nothing measured yet, for ``k`` pairs."""
        return cls(
            np.zeros((k, 2)), np.zeros((k, 2, 2)), np.full(k, np.nan), np.full(k, np.nan), {}
        )

    def keep(self, i: int, m: tuple[FloatArray, FloatArray, tuple[int, int]]) -> None:
        """Keep pair ``i``'s NCC map for the later passes, while the cache has room."""
        size = m[0].nbytes + m[1].nbytes
        if self.held + size <= MAP_CACHE_BYTES:
            self.maps[i] = m
            self.held += size


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
    if estimate_xy and len(pairs):
        translation[:, :2], complete, weighed = _xy_offsets(lat, corr, max_shift)
    translation[:, 2] = _z_offsets(lat, translation)
    measured = np.zeros(n, dtype=bool)
    measured[pairs[np.trace(corr.xy_w, axis1=1, axis2=2) > 0].ravel()] = True
    measurable = np.zeros(n, dtype=bool)
    can = np.array([lat.measurable(i) for i in range(len(pairs))], dtype=bool)
    measurable[pairs[can].ravel()] = True
    return CoarseStart(
        translation=translation,
        xy_measured=measured,
        xy_complete=complete,
        tilt=lat.tilt,
        xy_measurable=measurable,
        pair_information=weighed,
    )


def _xy_offsets(
    lat: Lattice, corr: Correlations, max_shift: float
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray]:
    """Every patch's XY (n, 2), metres, whether its pairs measured both axes, and every pair's
    information as the network weighed it (k, 2, 2): a first pass over all pairs, the network
    solved, the patches in doubt placed against all their neighbours, their pairs and the
    doubtful ones measured again, the network solved again."""
    n, pairs = len(lat.grids), lat.pairs
    radius = max_shift / lat.cell
    # every patch's stage error is a priori within about half the searched range
    xy_prior = 1.0 / (0.5 * max_shift) ** 2
    _first_pass(lat, corr, radius)
    drop_odd_scores(corr.score, corr.xy_w, excess=corr.excess, significance=SIGNIFICANCE)
    sol = solve_pair_differences(n, pairs, corr.xy_m, corr.xy_w, prior=xy_prior)
    unmeasured = np.trace(corr.xy_w, axis1=1, axis2=2) == 0
    doubtful = unmeasured | (sol.robust < DOUBT)
    x_start, moved = _place_doubtful(lat, corr, sol, unmeasured, radius)
    # second pass: doubtful pairs, and those of placed patches, re-measured near the shift the
    # network (mended by the placements) predicts
    redo = np.flatnonzero(doubtful | moved[pairs[:, 0]] | moved[pairs[:, 1]])
    if len(redo):
        for j in redo.tolist():
            checkpoint()
            pred = x_start[pairs[j, 0]] - x_start[pairs[j, 1]]
            e = lat.expected(j)
            centre = (e[0] + pred[1] / lat.cell, e[1] + pred[0] / lat.cell)
            _measure(lat, corr, j, centre, 2.0, radius=radius)
        sol = solve_pair_differences(n, pairs, corr.xy_m, corr.xy_w, prior=xy_prior)
    weighed = corr.xy_w * sol.robust[:, None, None]
    return (*drop_unconstrained(sol.x, pairs, weighed), weighed)


def _first_pass(lat: Lattice, corr: Correlations, radius: float) -> None:
    """Every measurable pair correlated (batched by image shapes through one set of FFTs) and
    its peak within ``radius`` cells of the nominal shift accepted or not."""
    todo = [i for i in range(len(lat.pairs)) if lat.measurable(i)]
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
        _accept(lat, corr, i, peak, radius=radius)
        if not corr.xy_w[i].any():  # a copy: the maps are views of their whole batch's
            corr.keep(i, (ncc.copy(), count.copy(), zero))


def _place_doubtful(
    lat: Lattice,
    corr: Correlations,
    sol: NetworkSolution,
    unmeasured: NDArray[np.bool_],
    radius: float,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The network's XY (n, 2) with the patches whose links found nothing or conflict placed
    against all their neighbours at once; and which patches moved."""
    n, pairs, cell = len(lat.grids), lat.pairs, lat.cell
    can_measure = np.array([lat.measurable(i) for i in range(len(pairs))], dtype=bool)
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


def _correlation(
    lat: Lattice, corr: Correlations, i: int
) -> tuple[FloatArray, FloatArray, tuple[int, int]]:
    """Pair ``i``'s NCC map, computed once (while the cache has room)."""
    if i in corr.maps:
        return corr.maps[i]
    a, b = lat.pairs[i]
    m = masked_ncc(lat.channels[a], lat.channels[b], weights=CHANNEL_WEIGHTS)
    corr.keep(i, m)
    return m


def _measure(
    lat: Lattice,
    corr: Correlations,
    i: int,
    centre: tuple[float, float],
    rad: float,
    *,
    radius: float,
) -> None:
    """Pair ``i`` measured again: its peak within ``rad`` cells of ``centre`` (dy, dx) (and the
    texture's along an edge within the first pass's ``radius``)."""
    peak = None
    if lat.measurable(i):
        peak = find_peak(
            *_correlation(lat, corr, i),
            expected=centre,
            radius=(rad, rad),
            min_overlap=int(lat.least_overlap[i]),
            prior=SHIFT_PRIOR,
            ambiguity=AMBIGUITY,
        )
    # the first pass's peak stood out of its window and this one scores well below it: the
    # overlap says the first, whatever the network predicts (it may be the network that errs)
    if (
        peak is not None
        and corr.excess[i] >= SIGNIFICANCE
        and peak.score < corr.score[i] - AMBIGUITY
    ):
        return
    _accept(lat, corr, i, peak, radius=radius)


def _accept(
    lat: Lattice, corr: Correlations, i: int, peak: CorrelationPeak | None, *, radius: float
) -> None:
    """Pair ``i``'s measurement from ``peak``: its shift and information, or none where the
    peak lies at the window's border or neither scores nor stands out of chance. Along a
    straight edge whose information is the texture's beside it, the shift is the texture's
    own, searched within ``radius`` cells (:mod:`merge.start.texture`), or not measured."""
    a, b = lat.pairs[i]
    corr.xy_w[i] = 0.0
    if peak is None or peak.at_border:
        return
    if peak.score < MIN_SCORE and peak.excess < SIGNIFICANCE:
        return
    cell = lat.cell
    corr.score[i], corr.excess[i] = peak.score, peak.excess
    s_pair = float(np.hypot(lat.sigma[a], lat.sigma[b]) / np.sqrt(2.0))
    info, edge = overlap_measurement(
        lat.levelled[a],
        lat.levelled[b],
        peak.integer_shift,
        s_pair,
        precision=PRECISION,
        aperture=APERTURE,
        texture=TEXTURE,
    )
    dy, dx = peak.shift
    if edge is not None:
        ta, tb = corr.texture(lat, a), corr.texture(lat, b)
        moved = None
        if ta is not None and tb is not None:
            moved = along_edge(
                ta,
                tb,
                peak,
                edge,
                radius=radius,
                min_overlap=int(lat.least_overlap[i]),
                accept=MIN_SCORE,
                significance=SIGNIFICANCE,
                ambiguity=AMBIGUITY,
            )
        across = np.eye(2) - np.outer(edge, edge)
        along = 0.0  # nothing measured along the edge ...
        if moved is not None:  # ... but what its texture measured
            dx, dy = dx + moved * edge[0], dy + moved * edge[1]
            along = max(float(edge @ info @ edge), ALONG_EDGE)
        info = across @ info @ across + along * np.outer(edge, edge)
    e = lat.expected(i)
    corr.xy_m[i] = [(dx - e[1]) * cell, (dy - e[0]) * cell]
    # a pair whose first pass found its shift ambiguous along a ridge stays so in the second
    # pass, whose narrow window cannot see the ridge: on a chessboard's face at 1 µm patches
    # (draw 3) a pair re-measured 16 cells along its ridge claimed both directions, and its
    # corner patch merged 375 nm off
    known = corr.ridges.get(i, ())
    corr.ridges[i] = known or peak.ridge
    corr.xy_w[i] = along_ridge_removed(info, known + peak.ridge) / cell**2


def _pair_map(lat: Lattice, corr: Correlations, i: int, c: int, x: FloatArray) -> PairMap:
    """Pair ``i`` seen from its patch ``c``, the other patch held at ``x`` (metres)."""
    a, b = int(lat.pairs[i, 0]), int(lat.pairs[i, 1])
    ncc, count, zero = _correlation(lat, corr, i)
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
    for i in range(k):
        checkpoint()
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        e = lat.expected(i)
        pred = translation[a, :2] - translation[b, :2]
        shift = (round(e[0] + pred[1] / cell), round(e[1] + pred[0] / cell))
        dz, cnt = overlap_z_difference(lat.grids[a].heights, lat.grids[b].heights, shift)
        if lat.nominal_overlap[i] > 0 and cnt >= 16 and np.isfinite(dz):
            # variance of a median of differences of two noisy maps: (π/2) · 2σ² / count
            var = np.pi * (sigma[a] ** 2 + sigma[b] ** 2) / 2.0 / cnt
            z_m[i], z_w[i] = dz, 1.0 / var
    z: FloatArray = solve_pair_differences(n, pairs, z_m, z_w).x[:, 0]
    return z
