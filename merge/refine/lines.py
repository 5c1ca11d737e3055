"""Scan lines as correlated noise: every residual of one source line shares that line's offset.

An AFM's feedback settles anew on every line, so each line of a scan carries its own height
offset (a few tenths of a nanometre), on top of the white noise of every pixel. In an overlap
all residuals of one source line (and the one or two destination lines beneath it) move
together. Least squares that count them as independent over-trust line means: a line whose
ends lie at different heights (across a step) drags XY with its offset, and the relative tilts
of vertical neighbours, held by a few dozen lines, follow the offsets into a mosaic-wide bowl.

The offsets are modelled as a random effect, not as unknowns: per group (one source line of one
directed pair), ``r = J δ + c + e`` with ``c ~ N(0, τ²)`` shared and ``e ~ N(0, σ² / w)`` per
row. Marginalising ``c`` (generalised least squares) takes from the group's information and
gradient the part its sums carry::

    Σ w J J' - (Σ w J)(Σ w J)' / (Σ w + ρ),    Σ w r J - (Σ w J)(Σ w r) / (Σ w + ρ),

with ``ρ = σ² / τ²``. Within-line variation (what XY is measured from) keeps all its weight;
the line means keep the weight of one sample of variance ``τ² + σ² / Σ w``. ``ρ`` is measured
on the residuals themselves (a robust one-way analysis of variance over the groups), so a scan
without line offsets gets none of this (``ρ`` infinite) and one with strong offsets trusts its
line means accordingly little.

Measured (map error over the floor, mean of 18 draws each; bilinear look-ups): TGX1 1.37 ->
1.34, harsh TGX1 1.37 -> 1.33; the 1-D grating's map as before, MoS2's XY 0.96 -> 0.90 nm.

A source line crosses several destinations (its two ends lie over the left and right
neighbours, a top line over three more), and its own offset is the same in all of them; only
the destination's lines beneath are a run's own. So a group's offset is two nested random
effects, ``c_line + d_group``: the group's own marginalised first (``ρ_run``), then the line's
over all its groups (``ρ_line``), which couples the runs of one source (two destinations of a
source, through the line that crosses both). Both variances are measured: the groups' means
give their sum, the differences of two groups of one line (apart, or the common noise of the
points they share hides the offsets) the runs' own part. The offset a line's two ends share
then measures the relative tilt of the patches beside it instead of being taken anew in each
(400 patches of 256 x 256 px, 3 draws: Z RMS 0.435 -> 0.412 nm, map/floor mean 1.19 -> 1.18,
worst 1.40 -> 1.35; 100 patches, 6 draws: 0.265 -> 0.258 nm; but 400 patches of 64 x 64 px, 10
draws: 0.52 -> 0.54 nm). With the simulator's 0.3 nm per line under 1 nm of white noise the
differences give the runs' own part a twentieth of the shared one (with 1 nm per line, 0.7):
split evenly instead, 64 x 64 px came out 0.53 nm and 100 patches of 256 x 256 px 0.256.

Why the runs' own part looks so small: the spread within the groups holds a misfit at the
scale of a pixel (the surface between the pixels, read at another sub-pixel place; along a
line the residuals' lag-one correlation is -0.45 on the folded surface), which cancels in a
group's mean, so ``σ² / Σw`` over-counts the means' noise by a quarter, and the variances are
measured net of that. Measured instead on the differences of a group's two halves (tried, not
kept), the noise is 1.36 nm against the spread's 1.67 and the split comes out as physics says
(own 0.055 nm², shared 0.077 against the simulator's 0.09 per line), but the merge does not
change (400 patches of 64 x 64 px, 10 draws: Z 0.541 -> 0.538 nm; 100 of 256 x 256 px, 6
draws: 0.258 -> 0.259): both splits give the groups' means the same variance and the means of
one line the same covariance (0.077 nm² either way), which is all the marginalisation uses.
What the 64 x 64 px mosaics lose is the model's, not the estimate's: a run's own part is the
destination's lines, which the reverse run holds as its shared part.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.core.progress import checkpoint
from merge.core.sparse import sum_at

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: Float arrays of any width (float32 where the mosaic's memory counts).
Floats = NDArray[np.floating[Any]]

#: Groups with fewer valid rows than this say little about the spread of their own rows.
MIN_GROUP = 5
#: Median of the chi-squared distribution with one degree of freedom.
MEDIAN_CHI2_1 = 0.454936
#: Groups the median of the offset variance is taken over, at most.
MEDIAN_GROUPS = 8192
#: Bisections of the offset variance (on its logarithm, over 30 orders of magnitude).
BISECTIONS = 26


def offset_ratio(
    r: FloatArray, w: Floats, valid: NDArray[np.bool_] | FloatArray, first: IntArray
) -> float:
    """``ρ = σ² / τ²``: white variance of a residual over the variance of its line's offset.

    One-way analysis of variance over the groups starting at ``first``: the pooled weighted
    spread within groups estimates ``σ²``; ``τ²`` is what makes the median of the groups'
    squared means over their variance, ``m² / (τ² + σ² / Σ w)``, that of χ²(1). A mean of them
    would take what a misfit leaves along some lines for offsets (along a 1-D grating's lines:
    ``ρ`` 5 instead of 11, and patches held too loosely across the stripes). ``inf`` when the
    means scatter no more than ``σ²`` explains (no line offsets) or too few groups hold enough
    rows.
    """
    return ratio_of_sums(group_sums(r, w, valid, first))


def group_sums(
    r: FloatArray, w: Floats, valid: NDArray[np.bool_] | FloatArray, first: IntArray
) -> FloatArray:
    """(4, g) per group starting at ``first``: ``Σ w``, ``Σ w r``, ``Σ w r²`` and its valid rows,
    what :func:`ratio_of_sums` needs (a mosaic's groups summed block by block)."""
    if len(first) == 0:
        return np.zeros((4, 0))
    return np.stack(
        [
            np.add.reduceat(w, first, dtype=np.float64),
            np.add.reduceat(w * r, first),
            np.add.reduceat(w * r * r, first),
            np.add.reduceat(valid, first, dtype=np.float64),
        ]
    )


def ratio_of_sums(sums: FloatArray) -> float:
    """:func:`offset_ratio` from the groups' sums (4, g) of :func:`group_sums`."""
    use, within = _within(sums)
    if not np.isfinite(within):
        return float("inf")
    sw, sr = sums[0, use], sums[1, use]
    # the groups' means: m² / (τ² + σ² / Σw) is χ²(1), whose median is MEDIAN_CHI2_1; a median
    # is not moved by the few groups a misfit or a defect puts far out
    tau2 = chi2_variance((sr / sw) ** 2, within / sw, within)
    return within / tau2 if tau2 > 0 else float("inf")


@dataclass(frozen=True)
class OffsetRatios:
    """``σ²`` over the variance of the offsets a group of rows has: ``run`` of the part its own
    run holds alone (the destination's lines beneath), ``line`` of the part every run of the
    source's line shares (the source line's own); infinite where there is none."""

    run: float
    line: float

    @property
    def any(self) -> bool:
        return bool(np.isfinite(self.run) or np.isfinite(self.line))


def shared_ratios(sums: FloatArray, lines: IntArray, spans: IntArray) -> OffsetRatios:
    """:class:`OffsetRatios` from the groups' sums (4, g), the scan line each group is
    (``lines`` (g,), :meth:`merge.refine.runs.Runs.lines`) and the columns it spans (``spans``
    (g, 2), first and past the last).

    A group's offset is its source line's, which every run over that line shares, minus the
    destination's lines beneath, which are the run's own. The groups' means give the sum of both
    variances (:func:`ratio_of_sums`); the differences of two groups of one line hold only the
    runs' own parts, ``(m_i - m_j)² / (2 τ_run² + σ² / Σw_i + σ² / Σw_j)`` being χ²(1), where
    the two share no point (a corner's rows are in the side's run too: their common noise made
    the differences look free of offsets, 1 nm of white noise hiding 0.3 nm per line); the
    shared part is what is left (none where the lines are never met twice).
    """
    use, within = _within(sums)
    if not np.isfinite(within):
        return OffsetRatios(float("inf"), float("inf"))
    sw, sr = sums[0, use], sums[1, use]
    mean, var = sr / sw, within / sw
    tau2 = chi2_variance(mean**2, var, within)
    if tau2 <= 0:
        return OffsetRatios(float("inf"), float("inf"))
    checkpoint()  # the pairs of a large mosaic's groups take a few tenths of a second
    i, j = _apart(lines[use], spans[use])
    checkpoint()
    if len(i) < 2:
        return OffsetRatios(within / tau2, float("inf"))
    d2, v = 0.5 * (mean[i] - mean[j]) ** 2, 0.5 * (var[i] + var[j])
    own = min(chi2_variance(d2, v, within), tau2)
    shared = tau2 - own
    return OffsetRatios(
        within / own if own > 0 else float("inf"),
        within / shared if shared > 1e-6 * tau2 else float("inf"),
    )


def _apart(lines: IntArray, spans: IntArray) -> tuple[IntArray, IntArray]:
    """Pairs of groups (p,) each of one line whose columns do not meet."""
    i, j = _line_pairs(lines)
    apart = (spans[i, 1] <= spans[j, 0]) | (spans[j, 1] <= spans[i, 0])
    return i[apart], j[apart]


def _line_pairs(lines: IntArray) -> tuple[IntArray, IntArray]:
    """Every pair of groups of one line (p,) each, the first of a pair the earlier group."""
    order = np.argsort(lines, kind="stable")
    pairs_i, pairs_j = [np.empty(0, dtype=np.intp)], [np.empty(0, dtype=np.intp)]
    for d in range(1, len(order)):  # the d-th next group of the same line, while there is one
        i, j = order[:-d], order[d:]
        same = lines[i] == lines[j]
        if not same.any():
            break
        pairs_i.append(i[same])
        pairs_j.append(j[same])
        checkpoint()
    return np.concatenate(pairs_i), np.concatenate(pairs_j)


def _within(sums: FloatArray) -> tuple[NDArray[np.bool_], float]:
    """The groups that say something of their rows' spread (``MIN_GROUP`` valid rows or more),
    and the pooled white variance ``σ²`` within them (``inf`` with fewer than two such groups
    or no spread)."""
    sw, sr, srr, n = sums
    use = (n >= MIN_GROUP) & (sw > 0)
    if use.sum() < 2:
        return use, float("inf")
    within = float((srr[use] - sr[use] ** 2 / sw[use]).sum() / (n[use] - 1).sum())
    return use, within if within > 0 else float("inf")


def chi2_variance(m2: FloatArray, v: FloatArray, scale: float) -> float:
    """``τ²`` that makes the median of ``m2 / (τ² + v)`` that of χ²(1) (0 where ``v`` alone
    explains ``m2``): squared means ``m2`` of noise ``v`` (g,) each and of a common spread,
    sought from ``1e-12 scale`` on."""
    if len(m2) > MEDIAN_GROUPS:  # evenly spread over the mosaic: a median needs no more
        pick = np.linspace(0, len(m2) - 1, MEDIAN_GROUPS).astype(np.intp)
        m2, v = m2[pick], v[pick]
    if np.median(m2 / v) <= MEDIAN_CHI2_1:
        return 0.0
    # bisection on log τ² (the median falls as τ² grows), to a few parts per million
    lo, hi = np.log(1e-12 * scale), np.log(float(np.max(m2)) + scale)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        if np.median(m2 / (np.exp(mid) + v)) > MEDIAN_CHI2_1:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


@dataclass(frozen=True)
class SharedLines:
    """What the offsets of scan lines shared between runs take out between those runs: per
    pair of runs of one source (``first`` < ``second``, c,) the block ``C`` (c, 6, 6) to take
    from ``B_first,second`` in the runs' relative unknowns (``y_k = x_src - T_k' x_dst``,
    :func:`merge.refine.assembly.assemble`), and its transpose from the other."""

    first: IntArray
    second: IntArray
    C: FloatArray

    @classmethod
    def none(cls) -> SharedLines:
        empty = np.empty(0, dtype=np.intp)
        return cls(empty, empty, np.empty((0, 6, 6)))

    def moved(self, by: int) -> SharedLines:
        """The same with the runs counted ``by`` later."""
        return SharedLines(self.first + by, self.second + by, self.C)

    @classmethod
    def joined(cls, parts: list[SharedLines]) -> SharedLines:
        if not parts:
            return cls.none()
        return cls(
            np.concatenate([p.first for p in parts]),
            np.concatenate([p.second for p in parts]),
            np.concatenate([p.C for p in parts]),
        )


def marginalise_offsets(
    J: FloatArray,
    w: Floats,
    r: FloatArray,
    runs: IntArray,
    first: IntArray,
    rho: OffsetRatios,
    B: FloatArray,
    g: FloatArray,
    lines: IntArray | None = None,
) -> SharedLines:
    """Take the line offsets out of per-run sums ``B`` (k, 6, 6) and ``g`` (k, 6), in place.

    ``J`` (m, 6), ``w`` and ``r`` (m,) are the rows of ``k`` runs (``runs`` (k + 1,) their
    bounds), ``first`` the first row of every group in them
    (:meth:`merge.refine.runs.Runs.groups`: every run starts one), ``rho`` from
    :func:`shared_ratios` (both infinite: nothing to do), ``lines`` (g,) which scan line every
    group is (:meth:`Runs.lines`; every group of one line among these runs). Two nested random
    effects: a group's own offset (``rho.run``) marginalised group by group, then the line's
    shared one (``rho.line``) over all its groups: within a run it changes ``B`` and ``g``,
    between two runs of one source it gives the blocks returned (none without ``lines``).
    """
    if not rho.any or len(first) == 0:
        return SharedLines.none()
    sj: FloatArray = np.add.reduceat(J * w[:, None], first, axis=0, dtype=np.float64)
    sw: FloatArray = np.add.reduceat(w, first, dtype=np.float64)
    sr: FloatArray = np.add.reduceat(w * r, first, dtype=np.float64)
    # the groups of each run are contiguous, and every run starts one
    run_first = np.searchsorted(first, runs[:-1])
    if np.isfinite(rho.run):
        f = 1.0 / (sw + rho.run)
        fj = sj * f[:, None]
        B -= np.add.reduceat(np.einsum("gi,gj->gij", fj, sj), run_first, axis=0)
        g -= np.add.reduceat(fj * sr[:, None], run_first, axis=0)
        # what the group's mean says of the shared offset once its own is taken out
        keep = rho.run * f
        sj, sw, sr = sj * keep[:, None], sw * keep, sr * keep
    if lines is None or not np.isfinite(rho.line):
        return SharedLines.none()
    line, at = np.unique(lines, return_inverse=True)
    shared = 1.0 / (np.bincount(at, weights=sw, minlength=len(line)) + rho.line)
    fj = sj * shared[at][:, None]
    total_r = np.bincount(at, weights=sr, minlength=len(line))
    B -= np.add.reduceat(np.einsum("gi,gj->gij", fj, sj), run_first, axis=0)
    g -= np.add.reduceat(fj * total_r[at][:, None], run_first, axis=0)
    return _between_runs(at, fj, sj, run_first, len(runs) - 1)


def _between_runs(
    at: IntArray, fj: FloatArray, sj: FloatArray, run_first: IntArray, k: int
) -> SharedLines:
    """:class:`SharedLines` of groups of one line ``at`` (g,) in different runs: ``fj_i sj_j'``
    summed per pair of runs."""
    run = np.repeat(np.arange(k), np.diff(np.append(run_first, len(at))))
    i, j = _line_pairs(at)
    if len(i) == 0:
        return SharedLines.none()
    # a run holds a line once, and the runs of a line follow the groups' order: run i < run j
    blocks = np.einsum("pi,pj->pij", fj[i], sj[j])
    pair, where = np.unique(run[i] * k + run[j], return_inverse=True)
    return SharedLines(pair // k, pair % k, sum_at(where, blocks, len(pair)))
