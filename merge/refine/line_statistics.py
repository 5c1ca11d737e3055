"""What the residuals of the overlaps say before the heights' last solve
(:mod:`merge.refine.heights`): their robust scale and white noise, one scan line's offset sigma,
how much a line's mean over an overlap is worth, and the XY blur that slopes turn into height.

The means of one source line's rows in one pair scatter by two lines' offsets (the source's,
and the destination's interpolated between two of its lines) and by their own white noise, once
a straight line across the pair's lines is taken out (the places' misfit, which the solve
corrects); ``τ²`` is what makes the median of their squares over their variance that of χ²(1)
(:func:`merge.refine.lines.chi2_variance`). The rows are weighted robustly on their deviations
from their line's mean (:func:`line_weights`), never on the residuals themselves.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.progress import checkpoint
from merge.refine.lines import MIN_GROUP, chi2_variance
from merge.refine.pair_rows import PairRows

FloatArray = NDArray[np.float64]

#: Cauchy scale in robust sigmas, as the refinement's (:func:`merge.refine.normal_system.cauchy`).
CAUCHY = 3.0


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
        checkpoint()
    spread = np.abs(np.concatenate(deviations)) if deviations else np.zeros(0)
    slope2 = np.concatenate(slopes) if slopes else np.zeros(0)
    del deviations, slopes  # a row's worth each, beside the rows themselves
    if len(spread) < 2 * MIN_GROUP:
        return LineStatistics(0.0, 0.0, 0.0)
    scale = 1.4826 * float(np.median(spread))
    if not scale > 0:
        return LineStatistics(0.0, 0.0, 0.0)
    xy = slope_blur(spread, slope2)
    del spread, slope2
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
    # none where the means' own noise explains them (chi2_variance says 0)
    tau2 = chi2_variance(m2, v, noise2) / float(np.mean(np.concatenate(share)))
    return LineStatistics(scale, noise, float(np.sqrt(max(tau2, 0.0))), mean_noise, xy)
