"""Tilts of patches levelled one by one, found from their overlaps before they are correlated.

Many programs level every scan on its own before export (a plane fitted and subtracted). On a
sample with large steps that plane is not the sample's: a patch holding part of a 600 nm step
comes out tilted by hundreds of nanometres across, each patch differently, and neighbours then
disagree by a ramp across their overlap that the correlation of heights cannot see past.

Such patches are recognised by what levelling leaves: every patch's own least-squares plane is flat
to rounding (:func:`levelled_one_by_one`); raw scans never are (sample tilt, drift). Only then are
tilts estimated. A tilt adds a constant to a patch's slopes, which their normalized correlation
ignores: each pair is registered on its slopes alone, and the median of their differences there
measures the pair's tilt difference (at the nominal shift, misplaced flanks would disagree by more).
All patches' tilts are solved at once from these differences (:mod:`merge.start.network`, robust,
mean tilt zero: levelled scans keep no sample tilt). On TGX1-like mosaics they come within about 10
nm of ramp across a patch (40 nm at worst) where levelling left hundreds; the refinement's drift
planes take them from there. On raw scans such errors would only add ramps, so nothing is estimated.

Pure functions of arrays (lattice cells, metres).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.downsample import GridSample
from merge.core.heightfield import smooth_nan
from merge.core.progress import checkpoint
from merge.start.ncc import pair_maps
from merge.start.network import solve_pair_differences
from merge.start.peaks import find_peak

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A patch whose own least-squares plane changes its heights by less than this fraction of their
#: range over the patch was levelled (rounding of float32 storage stays below 1e-6).
FLAT_TO_ROUNDING = 1e-5
#: Share of the patches that must be so for the set to count as levelled one by one.
LEVELLED_SHARE = 0.9
#: Fewest overlapping cells a slope difference is measured on.
MIN_CELLS = 16


def own_plane_change(heights: FloatArray) -> float:
    """How much a patch's own least-squares plane changes its heights across the patch, as a
    fraction of their range (0 for a patch levelled by that plane; NaN if it cannot tell)."""
    h = np.asarray(heights, dtype=np.float64)
    ok = np.isfinite(h)
    span = float(np.ptp(h[ok])) if ok.sum() >= 3 else 0.0
    if span == 0.0:
        return float("nan")
    yy, xx = np.nonzero(ok)
    x, y, z = xx - xx.mean(), yy - yy.mean(), h[ok] - h[ok].mean()
    A = np.array([[x @ x, x @ y], [x @ y, y @ y]])
    if np.linalg.cond(A) > 1e12:
        return float("nan")
    bx, by = np.linalg.solve(A, [x @ z, y @ z])
    return float((abs(bx) * np.ptp(xx) + abs(by) * np.ptp(yy)) / span)


def levelled_one_by_one(heights: Sequence[FloatArray]) -> bool:
    """Whether (nearly) every patch had its own least-squares plane subtracted."""
    change = np.empty(len(heights))
    for c, h in enumerate(heights):
        checkpoint()
        change[c] = own_plane_change(h)
    known = np.isfinite(change)
    if not known.any():
        return False
    return bool(np.mean(change[known] < FLAT_TO_ROUNDING) >= LEVELLED_SHARE)


def slope_difference(
    a: FloatArray, b: FloatArray, shift: tuple[int, int]
) -> tuple[FloatArray, float, int]:
    """Median of ``b``'s slopes minus ``a``'s over their overlap at ``shift``.

    Parameters
    ----------
    a, b : (my, mx) arrays
        Slope maps stacked as ``(2, my, mx)`` (d/dx, d/dy, height per cell); NaN where unknown.
    shift : (dy, dx)
        ``b[y + dy, x + dx]`` meets ``a[y, x]``.

    Returns the median difference (2,), the variance of that median (robust spread of the
    differences, per axis, averaged) and the number of cells used.
    """
    dy, dx = shift
    y0, y1 = max(0, -dy), min(a.shape[1], b.shape[1] - dy)
    x0, x1 = max(0, -dx), min(a.shape[2], b.shape[2] - dx)
    if y1 - y0 < 2 or x1 - x0 < 2:
        return np.zeros(2), np.inf, 0
    d = b[:, y0 + dy : y1 + dy, x0 + dx : x1 + dx] - a[:, y0:y1, x0:x1]
    ok = np.isfinite(d).all(axis=0)
    count = int(ok.sum())
    if count < MIN_CELLS:
        return np.zeros(2), np.inf, count
    d = d[:, ok]
    med = np.median(d, axis=1)
    spread = 1.4826 * np.median(np.abs(d - med[:, None]), axis=1)
    # a median's variance is π/2 that of a mean
    var = float(np.mean(spread**2)) * np.pi / 2.0 / count
    return med, max(var, 1e-30), count


def patch_tilts(
    grids: Sequence[GridSample],
    offsets: Sequence[tuple[int, int]],
    pairs: IntArray,
    usable: NDArray[np.bool_],
    *,
    radius: float,
    min_overlap: Sequence[int],
) -> FloatArray:
    """Every patch's tilt (dz/dx, dz/dy, dimensionless) relative to the mean, ``(n, 2)``.

    Parameters
    ----------
    grids : sequence of GridSample
        The patches on one lattice.
    offsets : sequence of (row, column)
        Lattice index of every grid's cell (0, 0).
    pairs : (k, 2) int array
    usable : (k,) bool
        Pairs whose nominal overlap is large enough to measure.
    radius : float, keyword-only
        Largest XY error of a pair searched, cells.
    min_overlap : sequence of int, keyword-only
        Fewest cells a pair's correlation peak must overlap, per pair.

    Each pair is registered on its slopes alone first (see the module's notes).
    """
    n, k = len(grids), len(pairs)
    slopes = []
    for g in grids:
        gy, gx = np.gradient(smooth_nan(g.heights, 1.0, border="mirror"))
        slopes.append(np.stack([gx, gy]))
    measured, weight = np.zeros((k, 2)), np.zeros(k)
    for i, ncc, count, zero in pair_maps(slopes, pairs, np.flatnonzero(usable).tolist()):
        a, b = int(pairs[i, 0]), int(pairs[i, 1])
        shift = (offsets[a][0] - offsets[b][0], offsets[a][1] - offsets[b][1])
        peak = find_peak(
            ncc,
            count,
            zero,
            expected=(float(shift[0]), float(shift[1])),
            radius=(radius, radius),
            min_overlap=int(min_overlap[i]),
        )
        if peak is not None and not peak.at_border:
            shift = peak.integer_shift
        med, var, _ = slope_difference(slopes[a], slopes[b], shift)
        if np.isfinite(var):
            measured[i], weight[i] = -med, 1.0 / var  # x_a - x_b
    if not weight.any():
        return np.zeros((n, 2))
    sol = solve_pair_differences(n, pairs, measured, weight)
    cell = np.array([g.cell for g in grids])
    tilt: FloatArray = sol.x / cell[:, None]
    return tilt


def untilted(grid: GridSample, tilt: FloatArray, centre: tuple[float, float]) -> GridSample:
    """The grid less the plane ``tilt · (xy - centre)`` (metres)."""
    yy, xx = np.meshgrid(grid.y - centre[1], grid.x - centre[0], indexing="ij")
    return dataclasses.replace(grid, heights=grid.heights - tilt[0] * xx - tilt[1] * yy)
