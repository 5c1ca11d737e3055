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
with the slope beneath it (the places' XY blur,
:func:`merge.refine.line_statistics.slope_blur`), a prior of ``1 / τ²`` on every line's offset
and the refinement's prior on the drift planes (along the lines one line's share of the drift
across them, as physics says, unless the patches' tilts showed otherwise). The system is sparse
(a line meets the lines of the patches it overlaps) and is factorised once.

The white noise of the residuals and the lines' variance ``τ²`` are measured on the residuals
at the start, on some pairs (:mod:`merge.refine.line_statistics`; the rows of a pair,
:mod:`merge.refine.pair_rows`). Where the offsets do not stand out of that noise
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
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csc_matrix, csr_matrix, diags

from merge.core.memory import release_freed
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.sparse import listened, solve_symmetric
from merge.core.transforms import PatchTransform
from merge.refine.line_statistics import LineStatistics, line_statistics, line_weights
from merge.refine.pair_rows import PairRows, pair_rows

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Pairs (spread evenly over the mosaic) the statistics of the residuals are measured on, and
#: their rows, at most: some thousands of lines' means (100 patches of 256 x 256 px: the lines'
#: sigma 0.292 nm from 256 pairs, 0.297 from 96; a mosaic of 64 x 64 px patches, where the
#: lines do not stand out, spent a tenth of a second of every live polish on 256). Held at
#: once, 256 pairs of 256 x 256 px took 9 bytes per pixel of 400 such patches.
SAMPLE_PAIRS = 96
SAMPLE_ROWS = 1 << 20
#: Triplets gathered before they are summed into the system built so far (a mosaic of 2,500
#: patches of 256 x 256 px gathers some sixty million).
COMPACT_EVERY = 4_000_000
#: White noise (metres) below which the scans count as free of it: a femtometre, far below
#: any instrument's and far above the rounding of heights held to the nanometre.
NOISE_FLOOR = 1e-15
#: Neighbouring lines of a patch the solve's fill-reducing ordering keeps together
#: (:func:`merge.core.sparse.grouped_order`; SuperLU's own ordering of every line holds the GIL
#: for seconds on a large mosaic, no cancel heard). 400 patches of 256 lines: 2 lines a group,
#: 0.06 s of it and a factor 11 % fuller; 4 lines, 0.03 s and 48 % fuller.
LINES_PER_GROUP = 2
#: Ridge on the Z offsets (a fraction of one point's weight): only the common offset, which no
#: data see, is held by it.
RIDGE = 1e-6


@dataclass(frozen=True)
class Heights:
    """The solve's outcome: the ``transforms`` with their Z offsets and drift planes moved,
    every patch's scan lines' offsets (metres, patch by patch, first line first), and the
    statistics it solved with."""

    transforms: list[PatchTransform]
    line_offsets: list[FloatArray]
    statistics: LineStatistics


def solve_heights(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    pairs: IntArray,
    *,
    plane_sigma: tuple[float, float],
    statistics: LineStatistics | None = None,
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
    statistics : LineStatistics, keyword-only
        The residuals' statistics, known (a simulator's, for an efficient solve to compare a
        merge with: ``scale`` infinite weighs every row alike), instead of measured on some
        pairs.

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
    stats = _measured(patches, transforms, pairs) if statistics is None else statistics
    if not (stats.lines_dominate and stats.noise > NOISE_FLOOR):
        return None
    lines = np.array([p.shape[0] for p in patches])
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
    del system  # its sum is A: held once
    # priors: every line's offset; the drift planes' total (now plus the step) towards none; a
    # ridge on the Z offsets for the common one
    # the radius the refinement's planes are counted at (SurfaceBank.radius: half the extent's
    # diagonal, first to last pixel centre), which the prior's sigmas are rises at
    radius = np.array([0.5 * np.hypot(*p.extent) for p in patches])
    slope = np.array([T.slope for T in transforms])
    prior = np.zeros(size)
    prior[3 * n :] = 1.0 / stats.tau**2
    prior[0 : 3 * n : 3] = RIDGE / stats.noise**2
    for k in (0, 1):
        prior[1 + k : 3 * n : 3] = (radius / sigma[k]) ** 2
        g[1 + k : 3 * n : 3] -= prior[1 + k : 3 * n : 3] * slope[:, k]
    checkpoint()
    # symmetric: its CSR arrays are its CSC ones, no conversion
    posterior = listened(partial(_plus_diagonal, A, prior))
    del A  # the system is held once while it is factorised
    arrays = (posterior.data, posterior.indices, posterior.indptr)
    x = solve_symmetric(csc_matrix(arrays, shape=posterior.shape), g, groups=_groups(lines))
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


def _plus_diagonal(A: csr_matrix, diagonal: FloatArray) -> csr_matrix:
    out: csr_matrix = A + diags(diagonal, format="csr")
    return out


def _groups(lines: IntArray) -> IntArray:
    """The unknowns' groups the solve's ordering is computed on
    (:func:`merge.core.sparse.grouped_order`): a patch's three, then every
    :data:`LINES_PER_GROUP` neighbouring lines of a patch (``lines`` (n,) per patch)."""
    n = len(lines)
    pairs = (lines + LINES_PER_GROUP - 1) // LINES_PER_GROUP
    start = n + np.concatenate([[0], np.cumsum(pairs)[:-1]])
    patch = np.repeat(np.arange(n), lines)
    within = np.arange(int(lines.sum())) - np.repeat(np.cumsum(lines) - lines, lines)
    out: IntArray = np.concatenate(
        [np.arange(3 * n) // 3, start[patch] + within // LINES_PER_GROUP]
    )
    return out


def _measured(
    patches: Sequence[Patch], transforms: Sequence[PatchTransform], pairs: IntArray
) -> LineStatistics:
    """The residuals' statistics on some of ``pairs`` (:func:`_sample`, at most
    :data:`SAMPLE_ROWS` rows)."""
    sampled: list[PairRows] = []
    white = []
    held = 0
    for a, b in _sample(pairs).tolist():
        kept = _rows_of(patches, transforms, (a, b))
        if kept is not None:
            sampled.append(kept.for_statistics())
            white.append((_white(patches[a]), _white(patches[b])))
            held += len(kept.r)
        checkpoint()
        if held >= SAMPLE_ROWS:
            break
    stats = line_statistics(sampled, white)
    del sampled
    # the sample's pages back to the system: on a mosaic whose lines do not stand out nothing
    # else of this solve follows, and what it freed stayed resident under the render and the
    # files written (100 patches of 64 x 64 px: 3 bytes per input pixel)
    release_freed()
    return stats


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
        self.g[P] -= V.T @ wr  # a and b differ: no index twice
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
        self._parts, self._pending = [], 0
        so_far = self._sum

        def summed() -> csr_matrix:
            part = coo_matrix((v, (r, c)), shape=(self.size, self.size)).tocsr()
            return part if so_far is None else so_far + part

        # tens of millions of nonzeros on a large mosaic: seconds, listening for a cancel
        self._sum = listened(summed)

    def matrix(self) -> csr_matrix:
        """The summed system (``size`` x ``size``)."""
        self._compact()
        return csr_matrix((self.size, self.size)) if self._sum is None else self._sum
