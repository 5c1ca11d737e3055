"""The patches on the coarse start's common lattice: levelled together, gaps filled, and the
channels that are correlated (heights and slopes); how much texture a patch holds; and what the
overlap of two patches at a shift measures (XY information, Z offset).

Pure functions of arrays; :mod:`merge.start.averaging` averages the patches onto the lattice
(:func:`merge.core.downsample.grid_downsample`) and :mod:`merge.start.coarse` correlates what
these return.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.downsample import GridSample
from merge.core.heightfield import smooth_nan
from merge.core.information import psd_part
from merge.core.progress import checkpoint

FloatArray = NDArray[np.float64]


def remove_common_plane(grids: Sequence[GridSample]) -> list[FloatArray]:
    """Heights minus one plane shared by all patches, fitted with a free offset per patch.

    A sample tilt is common to every patch, while the Z staircase is not; levelling each patch on
    its own would tilt patches differently around a large step and spoil the correlation.
    """
    sxx = sxy = syy = sxz = syz = 0.0
    for g in grids:
        checkpoint()  # 10,000 patches: a second for both loops
        yy, xx = np.meshgrid(g.y, g.x, indexing="ij")
        ok = np.isfinite(g.heights)
        if ok.sum() < 3:
            continue
        x, y, z = (
            xx[ok] - xx[ok].mean(),
            yy[ok] - yy[ok].mean(),
            g.heights[ok] - g.heights[ok].mean(),
        )
        sxx += float(x @ x)
        sxy += float(x @ y)
        syy += float(y @ y)
        sxz += float(x @ z)
        syz += float(y @ z)
    det = sxx * syy - sxy**2
    a, b = ((syy * sxz - sxy * syz) / det, (sxx * syz - sxy * sxz) / det) if det > 0 else (0, 0)
    out = []
    for g in grids:
        checkpoint()
        yy, xx = np.meshgrid(g.y, g.x, indexing="ij")
        out.append(g.heights - a * xx - b * yy)
    return out


def fill_empty_lines(grid: GridSample) -> GridSample:
    """The grid with rows and columns that no pixel fell in filled from their neighbours.

    With pixels longer than the cell along one axis (4:1 pixels, the cell set by the fine axis
    so that texture along it survives), whole lines of cells between scan lines stay empty; they
    are interpolated linearly along that axis. Holes within sampled lines stay holes.
    """
    h = grid.heights.copy()
    for axis in (0, 1):
        view = h if axis == 0 else h.T  # lines along ``axis`` are rows of ``view``
        full = np.isfinite(view).any(axis=1)
        if full.all() or full.sum() < 2:
            continue
        idx = np.flatnonzero(full)
        empty = np.flatnonzero(~full)
        inner = empty[(empty > idx[0]) & (empty < idx[-1])]
        below = idx[np.searchsorted(idx, inner) - 1]
        above = idx[np.searchsorted(idx, inner)]
        f = ((inner - below) / (above - below))[:, None]
        view[inner] = (1 - f) * view[below] + f * view[above]
    return dataclasses.replace(grid, heights=h)


def _about_plane(heights: FloatArray) -> FloatArray | None:
    """``heights`` less their own least-squares plane (NaN stays NaN); None below 4 values."""
    rows, cols = np.nonzero(np.isfinite(heights))
    if len(rows) < 4:
        return None
    A = np.column_stack([np.ones(len(rows)), cols, rows]).astype(np.float64)
    a, bx, by = np.linalg.lstsq(A, heights[rows, cols], rcond=None)[0]
    yy, xx = np.indices(heights.shape)
    out: FloatArray = heights - (a + bx * xx + by * yy)
    return out


def texture(heights: FloatArray) -> float:
    """Standard deviation of ``heights`` about their own least-squares plane (NaN-aware).

    The plane goes: an in-patch drift ramp on a featureless patch is not texture to correlate.
    """
    resid = _about_plane(heights)
    return 0.0 if resid is None else float(np.nanstd(resid))


def coherence(heights: FloatArray) -> float:
    """How one-dimensional ``heights`` are, in [0, 1]: ``(l1 - l2) / (l1 + l2)`` of the
    eigenvalues of their structure tensor (the sum of ``grad h grad h'``) about their own
    least-squares plane (NaN-aware). Near 1 on a grating's stripes or one straight edge, near 0
    on roughness; 0 without texture.
    """
    resid = _about_plane(heights)
    if resid is None or not np.nanstd(resid) > 1e-9 * np.nanstd(heights):  # a plane, to rounding
        return 0.0
    gy, gx = np.gradient(resid)
    J = np.array(
        [
            [np.nansum(gx * gx), np.nansum(gx * gy)],
            [np.nansum(gx * gy), np.nansum(gy * gy)],
        ]
    )
    low, high = np.linalg.eigvalsh(J)
    return float((high - low) / (high + low)) if high > 0 else 0.0


def correlated_channels(
    levelled: FloatArray, *, smooth: float | tuple[float, float] = 1.0
) -> FloatArray:
    """What is correlated: the heights and their slopes (after ``smooth`` cells of Gaussian
    smoothing, or (rows, columns) apart).

    Heights alone let a smooth background ramp correlate with itself at any shift (the NCC
    removes offsets, not ramps); slopes turn a ramp into a constant, which the NCC removes, and
    keep the wide, smooth edges of a grating that a high-pass filter would erase.
    """
    gy, gx = np.gradient(smooth_nan(levelled, smooth))
    return np.stack([levelled, gx, gy])


def _overlap(
    a_shape: tuple[int, ...], b_shape: tuple[int, ...], shift: tuple[int, int]
) -> tuple[slice, slice, slice, slice] | None:
    """Slices (rows and columns of ``a``, then of ``b``) where ``b[y + dy, x + dx]`` meets
    ``a[y, x]``; None if they do not overlap."""
    dy, dx = shift
    y0, y1 = max(0, -dy), min(a_shape[0], b_shape[0] - dy)
    x0, x1 = max(0, -dx), min(a_shape[1], b_shape[1] - dx)
    if y1 <= y0 or x1 <= x0:
        return None
    return slice(y0, y1), slice(x0, x1), slice(y0 + dy, y1 + dy), slice(x0 + dx, x1 + dx)


def overlap_information(
    a: FloatArray,
    b: FloatArray,
    shift: tuple[int, int],
    sigma: float,
    *,
    precision: float,
    aperture: float,
    texture: float = np.inf,
) -> FloatArray:
    """XY information (per cell², 2 x 2, order x, y) of a shift: structure tensor of the overlap.

    ``sigma`` is the noise of the difference of the two images, metres. Capped at
    ``1 / precision²`` (cells): a correlation peak on a lattice is never better than about a
    tenth of a cell (discretisation, interpolation bias), however sharp the edges. A direction
    with less than ``aperture`` of the larger information is not measured at all, unless its
    own texture is plain: at least ``texture`` times the slope energy the noise brings along
    it, and ``aperture`` of the capped information (a precision of ``precision / sqrt(aperture)``
    cells: a cell with the start's 0.1 and 0.01).
    """
    return _counted(_structure_information(a, b, shift, sigma), precision, aperture, texture)


def overlap_measurement(
    a: FloatArray,
    b: FloatArray,
    shift: tuple[int, int],
    sigma: float,
    *,
    precision: float,
    aperture: float,
    texture: float = np.inf,
) -> tuple[FloatArray, FloatArray | None]:
    """:func:`overlap_information` of one overlap (same arguments), and the unit direction
    (x, y) along a straight edge in it, or None: no edge, or structure both ways. An edge is a
    direction with less than ``aperture`` of the information across it, which is at least
    ``aperture`` of the cap ``1 / precision²``. The structure is found once for both."""
    found = _structure_information(a, b, shift, sigma)
    return _counted(found, precision, aperture, texture), _edge(found, precision, aperture)


def _counted(
    found: tuple[FloatArray, int] | None, precision: float, aperture: float, texture: float
) -> FloatArray:
    """What :func:`overlap_information` counts of an overlap's structure (``found``)."""
    if found is None:
        return np.zeros((2, 2))
    info, n = found
    # A direction with a tiny share of the information is not measured at all: pairs whose
    # nearly parallel edges are combined would otherwise amplify their errors along the edges.
    # But roughness on the faces beside a step measures the shift along the step, though the
    # step holds a hundred times more information across it: that texture, well above the
    # noise, counts (the noise's own share, n σ²/2 per direction, is n / 4 here).
    vals, vecs = np.linalg.eigh(info)
    cap = precision**-2
    plain = (vals >= texture * n / 4.0) & (np.minimum(vals, cap) >= aperture * cap)
    vals = np.where((vals >= aperture * vals.max()) | plain, np.minimum(vals, cap), 0.0)
    out: FloatArray = (vecs * vals) @ vecs.T
    return out


def _edge(
    found: tuple[FloatArray, int] | None, precision: float, aperture: float
) -> FloatArray | None:
    """The edge :func:`overlap_measurement` finds in an overlap's structure (``found``)."""
    if found is None:
        return None
    vals, vecs = np.linalg.eigh(found[0])
    cap = precision**-2
    if vals[0] < aperture * vals[1] and min(vals[1], cap) >= aperture * cap:
        out: FloatArray = vecs[:, 0]
        return out
    return None


def _structure_information(
    a: FloatArray, b: FloatArray, shift: tuple[int, int], sigma: float
) -> tuple[FloatArray, int] | None:
    """The XY information (2 x 2, per cell²) of the overlap of ``a`` and ``b`` at ``shift``,
    the noise's share taken out, and the cells it sums; None without an overlap.

    Both images must hold the structure: along each principal direction of the image that
    measures less (its smaller eigenvalue), the information is the lesser of the two images'
    (the same as either where they agree). From one image alone, a shift along a straight
    edge, rows short of the truth, let a corner of the first image's other edge into the
    overlap, which the second image did not hold there: the pair claimed a precision of 2 nm
    along the edge, and was 152 nm off (a chessboard with 100 nm ramps at the paper's grid,
    draw 1: its patch merged 87 nm off).

    And the two must agree at ``shift``: the information is at most what their slopes share
    (the symmetric part of their cross product, in which the noise of either averages out).
    Each image's own roughness is there at any shift; it measures only where it matches. In
    overlaps a few cells wide (15-20 % of a chessboard's patches at the paper's grid), the
    correlation's ridge along a straight edge rises with the overlap's size, its top lay
    240 nm along the edge from the truth, and the faces' roughness, each image's own, claimed
    that shift measured: blocks of columns merged 115 nm apart, each patch claiming 2 nm.

    And a slope the whole overlap shares measures nothing: shifted along it, the overlap only
    rises or falls, which its Z offset takes (the slopes are taken about their mean, the
    offset marginalised). In strips a few cells wide on a chessboard's 300 nm ramps, such a
    uniform slope claimed the shift along x of pairs that did not overlap at all (stage errors
    of 2.2 sigma): 300 nm off, a 2 x 5 mosaic's columns merged apart.
    """
    where = _overlap(a.shape, b.shape, shift)
    if where is None or where[0].stop - where[0].start < 3 or where[1].stop - where[1].start < 3:
        return None
    ya, xa, yb, xb = where
    both = np.stack([a[ya, xa], b[yb, xb]])
    # central differences on the overlap's inner cells (the noise's share below is theirs)
    gx = 0.5 * (both[:, 1:-1, 2:] - both[:, 1:-1, :-2])
    gy = 0.5 * (both[:, 2:, 1:-1] - both[:, :-2, 1:-1])
    g = np.stack([gx, gy], axis=1).reshape(2, 2, -1)  # (2 images, x and y, cells)
    valid = np.isfinite(g).all(axis=(0, 1))
    if not valid.all():
        g = g[:, :, valid]
    n = int(g.shape[2])
    g = g - g.mean(axis=2, keepdims=True)  # about their mean: a shared slope is an offset
    tensors = g @ g.transpose(0, 2, 1)
    # Noise is not texture: a central difference of white noise has variance σ²/2, which would
    # otherwise claim precision along a straight edge (the aperture problem) or on a flat terrace.
    infos = psd_part(tensors - n * sigma**2 / 2.0 * np.eye(2)) / (2.0 * sigma**2)
    vals, vecs = np.linalg.eigh(infos)
    weaker = vecs[int(np.argmin(vals[:, 0]))]
    each = np.einsum("ij,mik,kj->mj", weaker, infos, weaker)
    info: FloatArray = (weaker * each.min(axis=0)) @ weaker.T
    shared = g[0] @ g[1].T  # what the two share at this shift
    shared = psd_part(0.5 * (shared + shared.T)[None])[0] / (2.0 * sigma**2)
    info = _lesser(info, shared)
    return info, n


def overlap_z_difference(a: FloatArray, b: FloatArray, shift: tuple[int, int]) -> tuple[float, int]:
    """Median of ``b[y + dy, x + dx] - a[y, x]`` over the overlap, and the overlap size."""
    where = _overlap(a.shape, b.shape, shift)
    if where is None:
        return float("nan"), 0
    ya, xa, yb, xb = where
    diff = b[yb, xb] - a[ya, xa]
    diff = diff[np.isfinite(diff)]
    if diff.size == 0:
        return float("nan"), 0
    return float(np.median(diff)), int(diff.size)


def _lesser(p: FloatArray, q: FloatArray) -> FloatArray:
    """Of two 2 x 2 information matrices, along each principal direction of ``p`` the lesser
    (``q``'s there, never below zero)."""
    vals, vecs = np.linalg.eigh(p)
    along = np.einsum("ij,ik,kj->j", vecs, q, vecs)
    out: FloatArray = (vecs * np.minimum(vals, np.maximum(along, 0.0))) @ vecs.T
    return out
