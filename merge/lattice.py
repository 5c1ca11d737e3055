"""The patches on the coarse start's common lattice: levelled together, gaps filled, and the
channels that are correlated (heights and slopes); and how much texture a patch holds.

Pure functions of arrays; :mod:`merge.coarse` averages the patches onto the lattice
(:func:`merge.downsample.grid_downsample`) and correlates what these return.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.downsample import GridSample
from merge.heightfield import smooth_nan

FloatArray = NDArray[np.float64]


def remove_common_plane(grids: Sequence[GridSample]) -> list[FloatArray]:
    """Heights minus one plane shared by all patches, fitted with a free offset per patch.

    A sample tilt is common to every patch, while the Z staircase is not; levelling each patch on
    its own would tilt patches differently around a large step and spoil the correlation.
    """
    sxx = sxy = syy = sxz = syz = 0.0
    for g in grids:
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


def texture(heights: FloatArray) -> float:
    """Standard deviation of ``heights`` about their own least-squares plane (NaN-aware).

    The plane goes: an in-patch drift ramp on a featureless patch is not texture to correlate.
    """
    rows, cols = np.nonzero(np.isfinite(heights))
    if len(rows) < 4:
        return 0.0
    A = np.column_stack([np.ones(len(rows)), cols, rows]).astype(np.float64)
    z = heights[rows, cols]
    resid = z - A @ np.linalg.lstsq(A, z, rcond=None)[0]
    return float(np.std(resid))


def correlated_channels(levelled: FloatArray) -> FloatArray:
    """What is correlated: the heights and their slopes (after one cell of smoothing).

    Heights alone let a smooth background ramp correlate with itself at any shift (the NCC
    removes offsets, not ramps); slopes turn a ramp into a constant, which the NCC removes, and
    keep the wide, smooth edges of a grating that a high-pass filter would erase.
    """
    gy, gx = np.gradient(smooth_nan(levelled, 1.0))
    return np.stack([levelled, gx, gy])
