"""Each overlapping pair's XY shift and its information, from the peak of its correlation.

What the start has measured of its pairs so far is a :class:`Correlations`; :func:`accept`
turns a correlation peak (:mod:`merge.start.peaks`) into a pair's shift and its 2 x 2
information (:func:`merge.start.lattice.overlap_measurement`: only what both images hold and
share at the shift, a straight edge measuring only across itself unless the texture beside it
locates it along, :mod:`merge.start.texture`); :func:`measure` measures a pair again near a
predicted shift (the start's second pass, :func:`merge.start.coarse.coarse_start`), keeping a
first peak that stood out of chance against a weaker one near a prediction that may itself err.
The thresholds all these steps share are here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from merge.start.averaging import Lattice
from merge.start.lattice import overlap_measurement
from merge.start.ncc import masked_ncc
from merge.start.peaks import CorrelationPeak, find_peak
from merge.start.texture import along_edge, texture_image
from merge.start.trust import APERTURE, along_ridge_removed

FloatArray = NDArray[np.float64]

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
#: Bytes of NCC maps the first pass keeps for the second pass and the placements; past it they
#: are computed again when asked for (few are: the pairs in doubt). Kept all, a map of every
#: pair took 60 bytes per input pixel of a mosaic of 64 x 64 px patches, 2.4 GB at 10,000; the
#: first pass keeps only those of pairs it could not accept (the likely doubtful ones).
MAP_CACHE_BYTES = 64 << 20
#: Weights of the correlated channels: heights, x slope, y slope.
CHANNEL_WEIGHTS = (0.5, 0.25, 0.25)


@dataclass
class Correlations:
    """What correlating the pairs has measured so far.

    xy_m : (k, 2) each pair's XY shift off nominal, metres (x, y).
    xy_w : (k, 2, 2) its information, 1 / m² (zero: not measured).
    along_w : (k, 2, 2) the part of ``xy_w`` that the texture beside a straight edge measured
        along it (:func:`merge.start.texture.along_edge`; zero elsewhere).
    score : (k,) its peak's NCC (NaN: none accepted).
    excess : (k,) how far that peak stands above the best chance gives in its window
        (:attr:`merge.start.peaks.CorrelationPeak.excess`; NaN: none accepted).
    maps : the NCC maps computed, by pair (the second pass and the placements reuse them).
    ridges : per pair, the offsets (dy, dx) of the peaks the first pass found as likely as its
        own on its ridge (:attr:`merge.start.peaks.CorrelationPeak.ridge`), if any.
    repeats : per pair, the offsets (dy, dx) of the peaks as likely that a valley separates
        from its own (:attr:`merge.start.peaks.CorrelationPeak.repeats`), if any.
    """

    xy_m: FloatArray
    xy_w: FloatArray
    along_w: FloatArray
    score: FloatArray
    excess: FloatArray
    maps: dict[int, tuple[FloatArray, FloatArray, tuple[int, int]]]
    #: bytes the maps hold (:data:`MAP_CACHE_BYTES` at most)
    held: int = 0
    ridges: dict[int, tuple[tuple[int, int], ...]] = field(default_factory=dict)
    repeats: dict[int, tuple[tuple[int, int], ...]] = field(default_factory=dict)
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
            np.zeros((k, 2)),
            np.zeros((k, 2, 2)),
            np.zeros((k, 2, 2)),
            np.full(k, np.nan),
            np.full(k, np.nan),
            {},
        )

    def branch(self) -> Correlations:
        """A copy whose measurements can be changed apart from these (a hypothesis's second
        pass, :mod:`merge.start.hypotheses`); the NCC maps and textures, computed once, are
        shared."""
        return replace(
            self,
            xy_m=self.xy_m.copy(),
            xy_w=self.xy_w.copy(),
            along_w=self.along_w.copy(),
            score=self.score.copy(),
            excess=self.excess.copy(),
            ridges=dict(self.ridges),
            repeats=dict(self.repeats),
        )

    def keep(self, i: int, m: tuple[FloatArray, FloatArray, tuple[int, int]]) -> None:
        """Keep pair ``i``'s NCC map for the later passes, while the cache has room."""
        size = m[0].nbytes + m[1].nbytes
        if self.held + size <= MAP_CACHE_BYTES:
            self.maps[i] = m
            self.held += size


def correlation(
    lat: Lattice, corr: Correlations, i: int
) -> tuple[FloatArray, FloatArray, tuple[int, int]]:
    """Pair ``i``'s NCC map, computed once (while the cache has room)."""
    if i in corr.maps:
        return corr.maps[i]
    a, b = lat.pairs[i]
    m = masked_ncc(lat.channels[a], lat.channels[b], weights=CHANNEL_WEIGHTS)
    corr.keep(i, m)
    return m


def measure(
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
            *correlation(lat, corr, i),
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
    accept(lat, corr, i, peak, radius=radius)


def accept(
    lat: Lattice, corr: Correlations, i: int, peak: CorrelationPeak | None, *, radius: float
) -> None:
    """Pair ``i``'s measurement from ``peak``: its shift and information, or none where the
    peak lies at the window's border or neither scores nor stands out of chance. Along a
    straight edge whose information is the texture's beside it, the shift is the texture's
    own, searched within ``radius`` cells (:mod:`merge.start.texture`), or not measured."""
    a, b = lat.pairs[i]
    corr.xy_w[i] = 0.0
    corr.along_w[i] = 0.0
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
    # and so its repeats, which lie beyond that window too
    corr.repeats[i] = corr.repeats.get(i, ()) or peak.repeats
    ridge = known + peak.ridge
    corr.xy_w[i] = along_ridge_removed(info, ridge) / cell**2
    if edge is not None:  # what of it the texture measured, if anything
        corr.along_w[i] = along_ridge_removed(along * np.outer(edge, edge), ridge) / cell**2
