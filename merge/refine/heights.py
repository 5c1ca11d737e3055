"""The heights' last solve: every patch's Z offset and drift plane with every scan line's
offset, jointly, at the places the refinement reached.

Each scan line carries its own offset (the feedback settles anew on every line). In an overlap
a tilt of one patch against the other about x is a ramp across lines, which the lines' offsets
mimic; the refinement takes the offsets out as random effects run by run
(:mod:`merge.refine.lines`), where a line is one source line's, the destination's lines beneath
being that run's own. But a line's offset is one number wherever the line lies: the bottom
lines of a patch lie over its lower neighbour and, at their ends, over its left and right ones,
whose lines they are compared with line for line. Solved as unknowns of their own (with their
Gaussian prior), the offsets tie all of it together, and what only their randomness told apart
-- the patch rows' relative tilts, which add up to a mosaic-wide bend -- is told apart as well
as the data allow (the Cramér-Rao bound's own model, ``benchmarks/cramer_rao.py``).

With the places fixed the heights are linear in these unknowns, so one weighted least-squares
solve settles them: a residual of a point of patch ``a`` read in patch ``b`` (bilinear, each
pair once),

    r = z_a + dz_a + s_a · (p_a - c_a) - c_a[line] - (z_b + dz_b + s_b · (p_b - c_b)
        - (1 - f) c_b[j] - f c_b[j + 1]),

with Cauchy weights on every row's deviation from its line's mean, a variance that grows
with the slope beneath it (the places' XY blur, :func:`slope_blur`), a prior of ``1 / τ²`` on
every line's offset and the refinement's prior on the drift planes (along the lines one line's
share of the drift across them, as physics says, unless the patches' tilts showed otherwise).
The system is sparse (a line meets the lines of the patches it overlaps) and is factorised
once.

The white noise of the residuals and the lines' variance ``τ²`` are measured on the residuals
at the start (:func:`line_statistics`): the means of one source line's rows in one pair scatter
by two lines' offsets and their own noise once a straight line across the pair's lines is taken
out (the places' misfit, which this solve corrects); ``τ²`` is what makes the median of their
squares over their variance that of χ²(1). Where the offsets do not stand out of that noise
(``τ`` below a line's mean's white noise: patches of 64 x 64 px, whose overlaps are 16 px wide,
and the paper grid's of 60 x 30 px), the refinement's random effects told as much, and its
heights stand.

Measured (folded surface, 1 µm patches of 256 x 256 px, 25 % overlap, seed 1): 100 patches Z
0.27 -> 0.10 nm, map/floor 1.079 -> 1.011; 400 patches Z 0.59 -> 0.40 nm, 1.358 -> 1.175 (the
bound's 0.31 nm and 1.082; seeds 2-4 1.156 -> 1.128, 1.027 -> 1.041, 1.173 -> 1.199, Z RMS
over the four 0.42 -> 0.36 nm); 2,500 patches Z 0.96 -> 0.67 nm, 1.768 -> 1.433, the merge 207 ->
273 s. The bench's cases as before or better (1 µm TGX1 Z median 0.13 -> 0.10 nm); the grating
sweep's 1 µm chessboards (4 x 4 patches of 200 x 200 px, 10 draws): worsts 1.15 -> 1.10, 1.15
-> 1.08, 1.18 -> 1.10, 1.20 -> 1.18, 1.16 -> 1.13, medians within 1.5 %, but on two draws of
one case (3 µm period, 0.6 µm steps, 100 nm ramps) the rows bowled by 0.3 nm where they had not
(worst map/floor 1.24 -> 1.29): four rows' relative tilts, which the lines' offsets leave in
doubt, came out worse there and better on the case's five other draws that moved.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csc_matrix, csr_matrix

from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.sparse import solve_symmetric
from merge.core.transforms import PatchTransform
from merge.refine.lines import MEDIAN_CHI2_1, MIN_GROUP, chi2_variance

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Pairs (spread evenly over the mosaic) the statistics of the residuals are measured on, and
#: their rows, at most: some thousands of lines' means (100 patches of 256 x 256 px: the lines'
#: sigma 0.292 nm from 256 pairs, 0.297 from 96; a mosaic of 64 x 64 px patches, where the
#: lines do not stand out, spent a tenth of a second of every live polish on 256). Held at
#: once, 256 pairs of 256 x 256 px took 9 bytes per pixel of 400 such patches.
SAMPLE_PAIRS = 96
SAMPLE_ROWS = 1 << 20
#: Cauchy scale in robust sigmas, as the refinement's (:func:`merge.refine.normal_system.cauchy`).
CAUCHY = 3.0
#: Pixels added around the part of a patch that can lie over another.
GROW = 2
#: Triplets gathered before they are summed into the system built so far (a mosaic of 2,500
#: patches of 256 x 256 px gathers some sixty million).
COMPACT_EVERY = 4_000_000
#: White noise (metres) below which the scans count as free of it: a femtometre, far below
#: any instrument's and far above the rounding of heights held to the nanometre.
NOISE_FLOOR = 1e-15
#: Ridge on the Z offsets (a fraction of one point's weight): only the common offset, which no
#: data see, is held by it.
RIDGE = 1e-6


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


@dataclass(frozen=True)
class LineStatistics:
    """The residuals' robust scale and white sigma (metres), one scan line's offset sigma
    ``tau`` (metres; 0 where the lines carry none) and the white noise of a line's mean in a
    pair (``mean_noise``, metres: the median over the lines measured); ``xy``, the blur
    (metres) by which the rows' spread grows with the slope beneath them (:func:`slope_blur`).
    """

    scale: float
    noise: float
    tau: float
    mean_noise: float = np.inf
    xy: float = 0.0

    @property
    def lines_dominate(self) -> bool:
        """Whether the lines' offsets are the larger part of their means' scatter: only then
        does solving for them tell more than the refinement's random effects did."""
        return bool(self.tau > self.mean_noise)


@dataclass(frozen=True)
class Heights:
    """The solve's outcome: the ``transforms`` with their Z offsets and drift planes moved,
    every patch's scan lines' offsets (metres, patch by patch, first line first), and the
    statistics it solved with."""

    transforms: list[PatchTransform]
    line_offsets: list[FloatArray]
    statistics: LineStatistics


def pair_rows(a: Patch, b: Patch, T_a: PatchTransform, T_b: PatchTransform) -> PairRows | None:
    """:class:`PairRows` of ``a``'s pixels that fall inside ``b`` (all four of ``b``'s
    pixels around them measured), None if fewer than :data:`MIN_GROUP`. Both transforms turn
    about z only (the refinement's)."""
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
    inside = (u >= 0) & (u <= nxb - 1) & (v >= 0) & (v <= nyb - 1)
    i0 = np.clip(np.floor(u).astype(np.intp), 0, nxb - 2)
    j0 = np.clip(np.floor(v).astype(np.intp), 0, nyb - 2)
    fu, fv = u - i0, v - j0
    zb = (
        hb[j0, i0] * (1 - fu) * (1 - fv)
        + hb[j0, i0 + 1] * fu * (1 - fv)
        + hb[j0 + 1, i0] * (1 - fu) * fv
        + hb[j0 + 1, i0 + 1] * fu * fv
    )
    za = ha[line, x]
    ok = inside & np.isfinite(zb) & np.isfinite(za)
    if ok.sum() < MIN_GROUP:
        return None
    i0, j0, fu, fv = i0[ok], j0[ok], fu[ok], fv[ok]
    # the bilinear cell's slopes
    gx = (hb[j0, i0 + 1] - hb[j0, i0]) * (1 - fv) + (hb[j0 + 1, i0 + 1] - hb[j0 + 1, i0]) * fv
    gy = (hb[j0 + 1, i0] - hb[j0, i0]) * (1 - fu) + (hb[j0 + 1, i0 + 1] - hb[j0, i0 + 1]) * fu
    slope2 = (gx / b.pixel_size[0]) ** 2 + (gy / b.pixel_size[1]) ** 2
    da, db = pa[ok] - T_a.centre, pb[ok] - T_b.centre
    r = (za[ok] + T_a.t[2] + da @ T_a.slope) - (zb[ok] + T_b.t[2] + db @ T_b.slope)
    return PairRows(r, line[ok], j0, fv, da, db, slope2)


def line_weights(p: PairRows, scale: float, xy: float = 0.0) -> FloatArray:
    """(m,) Cauchy weights of a pair's rows on their deviations from their source line's mean
    (robust scale ``scale``, metres, widened on slopes by an XY blur ``xy``): a line's offset
    and the pair's misplacement move every row of a line alike, and weighed on the residuals
    themselves they would take weight from the lines whose offsets are large, shrinking what
    is measured of them (400 patches of 256 x 256 px: the lines' sigma 0.25 nm for 0.3, Z
    0.38 nm against 0.34). Two rounds: the plain mean, then the mean the first weights give."""
    at = p.line - p.line.min()
    w = np.ones_like(p.r)
    width = CAUCHY * np.sqrt(scale**2 + p.blurred(xy))
    for _ in range(2):
        mean = np.bincount(at, weights=w * p.r) / np.maximum(np.bincount(at, weights=w), 1e-300)
        w = 1.0 / (1.0 + ((p.r - mean[at]) / width) ** 2)
    return w


def slope_blur(deviations: FloatArray, slope2: FloatArray) -> float:
    """The XY blur (metres) by which rows' deviations from their line's mean (m,) spread more
    on steeper slopes (``slope2`` (m,), squared): ``d² = a + s² |slope|²`` through the robust
    variances of eight bins of rows by slope, ``s`` no less than 0. Heights are read at the
    places the refinement left, whose XY errors (and the look-ups' misfit on ramps) a slope
    turns into height: a grating's flank, 600 nm high over 100 nm, reads a tenth of a
    nanometre off as well as most of one."""
    if len(deviations) < 8 * MIN_GROUP:
        return 0.0
    bins = np.array_split(np.argsort(slope2), 8)
    v = np.array([(1.4826 * float(np.median(np.abs(deviations[k])))) ** 2 for k in bins])
    g = np.array([float(np.median(slope2[k])) for k in bins])
    if not np.ptp(g) > 0:
        return 0.0
    rise = float(np.polyfit(g, v, 1)[0])
    return float(np.sqrt(rise)) if rise > 0 else 0.0


def line_statistics(
    rows: Sequence[PairRows], white: Sequence[tuple[float, float]] | None = None
) -> LineStatistics:
    """:class:`LineStatistics` from the rows of some pairs: the robust scale of the rows'
    deviations from their source line's mean in the pair, and their white sigma once weighted
    (:func:`line_weights`); and the offset sigma one line has, from those lines' means, each
    pair's straight line across its lines taken out (:func:`chi2_variance`), shared between
    the two lines a mean holds (the source's and the destination's, interpolated). ``white``
    (one per pair of ``rows``): either scan's white noise (metres), which the means' noise is
    counted from (the source's, and the destination's as interpolated between two of its
    lines); default the rows' white sigma for both."""
    deviations, slopes = [], []
    for p in rows:
        at = p.line - p.line.min()
        n = np.bincount(at)
        mean = np.bincount(at, weights=p.r) / np.maximum(n, 1)
        keep = n[at] >= MIN_GROUP
        deviations.append((p.r - mean[at])[keep])
        slopes.append(p.blurred(1.0)[keep])  # the squared slopes
    spread = np.abs(np.concatenate(deviations)) if deviations else np.zeros(0)
    if len(spread) < 2 * MIN_GROUP:
        return LineStatistics(0.0, 0.0, 0.0)
    scale = 1.4826 * float(np.median(spread))
    if not scale > 0:
        return LineStatistics(0.0, 0.0, 0.0)
    xy = slope_blur(spread, np.concatenate(slopes))
    means, variances, share, within = [], [], [], []
    for i, p in enumerate(rows):
        w = line_weights(p, scale, xy)
        at = p.line - p.line.min()
        n = np.bincount(at)
        sw = np.bincount(at, weights=w)
        sr = np.bincount(at, weights=w * p.r)
        sw2 = np.bincount(at, weights=w * w)
        mix = np.bincount(at, weights=(1 - p.f) ** 2 + p.f**2) / np.maximum(n, 1)
        use = n >= MIN_GROUP
        if use.sum() < 3:
            continue
        inner = use[at]
        # one row's share of its line's mean taken back: the spread about the others' mean
        lift = 1.0 / (1.0 - (w / sw[at])[inner])
        within.append(np.abs(p.r - (sr / np.maximum(sw, 1e-300))[at])[inner] * np.sqrt(lift))
        m, y = sr[use] / sw[use], np.flatnonzero(use).astype(np.float64)
        # the pair's own misplacement: an offset and a tilt across its lines
        X = np.column_stack([np.ones_like(y), y - y.mean()]) * np.sqrt(sw[use])[:, None]
        coef = np.linalg.lstsq(X, m * np.sqrt(sw[use]), rcond=None)[0]
        d = m - coef[0] - coef[1] * (y - y.mean())
        # the fit took two of the means' degrees of freedom
        k = len(d)
        means.append(d * np.sqrt(k / (k - 2)) if k > 2 else d)
        of_a, of_b = (np.nan, np.nan) if white is None else white[i]
        # a mean's white variance, its rows' blur on slopes included
        blur = np.bincount(at, weights=w * w * p.blurred(xy)) / sw**2
        variances.append(
            np.column_stack([sw2[use] / sw[use] ** 2, of_a**2 + mix[use] * of_b**2, blur[use]])
        )
        share.append(1.0 + mix[use])
        checkpoint()
    if not means:
        return LineStatistics(scale, scale, 0.0)
    noise2 = (1.4826 * float(np.median(np.concatenate(within)))) ** 2
    m2 = np.concatenate(means) ** 2
    parts = np.concatenate(variances)
    # each mean's white variance: its scans' own where known, else the rows' spread's
    known = np.isfinite(parts[:, 1]) & (parts[:, 1] > 0)
    v = parts[:, 0] * np.where(known, parts[:, 1], noise2) + parts[:, 2]
    mean_noise = float(np.sqrt(np.median(v)))
    noise = float(np.sqrt(noise2))
    if np.median(m2 / v) <= MEDIAN_CHI2_1:
        return LineStatistics(scale, noise, 0.0, mean_noise, xy)
    tau2 = chi2_variance(m2, v, noise2) / float(np.mean(np.concatenate(share)))
    return LineStatistics(scale, noise, float(np.sqrt(max(tau2, 0.0))), mean_noise, xy)


def solve_heights(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    pairs: IntArray,
    *,
    plane_sigma: tuple[float, float],
) -> Heights | None:
    """Every patch's Z offset and drift plane, with every scan line's offset, solved jointly
    at the places of ``transforms`` (module docstring).

    Parameters
    ----------
    patches : sequence of Patch
    transforms : sequence of PatchTransform
        ``T_mosaic_patch`` per patch, turning about z only: the refinement's.
    pairs : (k, 2) int array
        The pairs that may overlap (each once).
    plane_sigma : (x, y), keyword-only
        Prior sigmas of the drift planes, metres: the plane's rise from its centre to the
        patch's corner, along each axis.

    Returns
    -------
    Heights, or None where the lines' offsets do not stand out of their means' noise (or
    none at all, or no pair overlaps, or the scans are free of noise, which leaves nothing to
    weigh the rows by): the refinement's heights then stand.
    """
    n = len(patches)
    if len(transforms) != n:
        raise ValueError(f"needs one transform per patch: {len(transforms)} for {n} patches")
    sigma = np.asarray(plane_sigma, dtype=np.float64)
    if sigma.shape != (2,) or not np.all(sigma > 0):
        raise ValueError(f"plane_sigma must be two positive sigmas, got {plane_sigma!r}")
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    if len(pairs) == 0:
        return None
    sampled: list[PairRows] = []
    white = []
    for a, b in _sample(pairs).tolist():
        kept = _rows_of(patches, transforms, (a, b))
        if kept is not None:
            sampled.append(kept)
            white.append((_white(patches[a]), _white(patches[b])))
        if sum(len(p.r) for p in sampled) >= SAMPLE_ROWS:
            break
    stats = line_statistics(sampled, white)
    del sampled
    if not (stats.lines_dominate and stats.noise > NOISE_FLOOR):
        return None
    lines = np.array([np.asarray(p.heights).shape[0] for p in patches])
    first = np.concatenate([[0], np.cumsum(lines)])
    size = 3 * n + int(first[-1])
    system = _System(size)
    for a, b in pairs.tolist():
        rows = _rows_of(patches, transforms, (a, b))
        if rows is not None:
            lab = (int(lines[a]), int(lines[b]))
            # the two scans' noise, each as it is at its pixels: interpolating b's averages
            # it, but with its neighbours', which is no information
            variance = _white(patches[a]) ** 2 + _white(patches[b]) ** 2
            la, lb = 3 * n + int(first[a]), 3 * n + int(first[b])
            system.add(rows, a, b, la, lb, lab, stats, variance if variance > 0 else stats.noise**2)
        checkpoint()
    A, g = system.matrix(), system.g
    # priors: every line's offset; the drift planes' total (now plus the step) towards none; a
    # ridge on the Z offsets for the common one
    radius = np.array(
        [
            0.5
            * np.hypot(
                np.asarray(p.heights).shape[1] * p.pixel_size[0],
                np.asarray(p.heights).shape[0] * p.pixel_size[1],
            )
            for p in patches
        ]
    )
    slope = np.array([T.slope for T in transforms])
    prior = np.zeros(size)
    prior[3 * n :] = 1.0 / stats.tau**2
    prior[0 : 3 * n : 3] = RIDGE / stats.noise**2
    for k in (0, 1):
        prior[1 + k : 3 * n : 3] = (radius / sigma[k]) ** 2
        g[1 + k : 3 * n : 3] -= prior[1 + k : 3 * n : 3] * slope[:, k]
    A = (A + coo_matrix((prior, (np.arange(size), np.arange(size))), shape=(size, size))).tocsc()
    checkpoint()
    x = solve_symmetric(csc_matrix(A), g)
    out = []
    for k, T in enumerate(transforms):
        t = T.t.copy()
        t[2] += x[3 * k]
        out.append(PatchTransform(T.R, t, T.slope + x[3 * k + 1 : 3 * k + 3], T.centre))
    offsets = [x[3 * n + first[k] : 3 * n + first[k + 1]].copy() for k in range(n)]
    return Heights(out, offsets, stats)


def _sample(pairs: IntArray) -> IntArray:
    """Up to :data:`SAMPLE_PAIRS` of ``pairs`` (k, 2), spread evenly over them and taken in
    an order that spreads every prefix too (first, last, middle, quarters, ...)."""
    k = min(len(pairs), SAMPLE_PAIRS)
    pick = np.unique(np.linspace(0, len(pairs) - 1, k).astype(np.intp))
    # bit-reversed order of the picks: any prefix lies all over the mosaic
    bits = max(1, int(np.ceil(np.log2(len(pick)))))
    order = np.argsort([int(f"{i:0{bits}b}"[::-1], 2) for i in range(len(pick))], kind="stable")
    out: IntArray = pairs[pick[order]]
    return out


def _white(patch: Patch) -> float:
    """A patch's white noise (metres), 0 where it has none or none could be estimated."""
    noise = patch.noise
    return noise if np.isfinite(noise) else 0.0


def _rows_of(
    patches: Sequence[Patch], transforms: Sequence[PatchTransform], pair: IntArray | tuple[int, int]
) -> PairRows | None:
    a, b = int(pair[0]), int(pair[1])
    return pair_rows(patches[a], patches[b], transforms[a], transforms[b])


class _System:
    """The normal equations of the heights' unknowns (per patch ``dz``, ``s_x``, ``s_y``; then
    every line's offset), gathered pair by pair as triplets and summed every
    :data:`COMPACT_EVERY` of them."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.g = np.zeros(size)
        self._parts: list[tuple[IntArray, IntArray, FloatArray]] = []
        self._pending = 0
        self._sum: csr_matrix | None = None

    def add(
        self,
        p: PairRows,
        a: int,
        b: int,
        la: int,
        lb: int,
        lines: tuple[int, int],
        s: LineStatistics,
        variance: float,
    ) -> None:
        """Pair ``(a, b)``'s rows; ``la`` and ``lb`` the unknowns of either patch's first line,
        ``lines`` how many lines either has, ``variance`` a residual's white variance."""
        w = line_weights(p, s.scale, s.xy) / (variance + p.blurred(s.xy))
        na, nb = lines
        # the patches' six unknowns and their coefficients per row
        V = np.column_stack([np.ones_like(p.r), p.da, -np.ones_like(p.r), -p.db])
        P = 3 * np.array([a, a, a, b, b, b]) + np.array([0, 1, 2, 0, 1, 2])
        wV = V * w[:, None]
        block = V.T @ wV
        self._put(np.repeat(P, 6), np.tile(P, 6), block.ravel())
        wr = w * p.r
        np.add.at(self.g, P, -(V.T @ wr))
        # the three lines of every row: a's own, b's below and the next, with their coefficients
        slots = (
            (la, p.line, -np.ones_like(p.f), na),
            (lb, p.j, 1.0 - p.f, nb),
            (lb, p.j + 1, p.f, nb),
        )
        for base, line, c, count in slots:
            self.g[base : base + count] -= np.bincount(line, weights=c * wr, minlength=count)
            # with the patches' unknowns
            key = (line[:, None] * 6 + np.arange(6)).ravel()
            cross = np.bincount(key, weights=(c[:, None] * wV).ravel(), minlength=6 * count)
            cross = cross.reshape(count, 6).T
            used = np.flatnonzero(cross.any(axis=0))
            self._put(
                np.repeat(base + used, 6),
                np.tile(P, len(used)),
                cross[:, used].T.ravel(),
                both=True,
            )
        # lines with lines, each pair of slots once (and mirrored)
        for s1 in range(3):
            for s2 in range(s1, 3):
                base1, line1, c1, _ = slots[s1]
                base2, line2, c2, count2 = slots[s2]
                key = line1 * (count2 + 1) + line2
                summed = np.bincount(key, weights=c1 * c2 * w)
                where = np.flatnonzero(summed)
                r1, r2 = base1 + where // (count2 + 1), base2 + where % (count2 + 1)
                self._put(r1, r2, summed[where], both=s1 != s2)

    def _put(
        self, rows: IntArray, cols: IntArray, vals: NDArray[Any], *, both: bool = False
    ) -> None:
        """Triplets into the system; ``both``: their mirror image too."""
        if both:
            rows, cols, vals = (
                np.concatenate([rows, cols]),
                np.concatenate([cols, rows]),
                np.concatenate([vals, vals]),
            )
        self._parts.append(
            (rows.astype(np.intp), cols.astype(np.intp), np.asarray(vals, dtype=np.float64))
        )
        self._pending += len(rows)
        if self._pending >= COMPACT_EVERY:
            self._compact()

    def _compact(self) -> None:
        if not self._parts:
            return
        r = np.concatenate([p[0] for p in self._parts])
        c = np.concatenate([p[1] for p in self._parts])
        v = np.concatenate([p[2] for p in self._parts])
        part = coo_matrix((v, (r, c)), shape=(self.size, self.size)).tocsr()
        self._sum = part if self._sum is None else (self._sum + part)
        self._parts, self._pending = [], 0

    def matrix(self) -> coo_matrix:
        self._compact()
        if self._sum is None:
            return coo_matrix((self.size, self.size))
        return coo_matrix(self._sum)
