"""Grid-based average down-sampling (paper, section III-C).

A square grid of side ``cell`` is laid over a patch; every point inside a cell is replaced by one
point at the cell centre whose height is the mean of the heights that fell in it (NaN ignored).
The result is an equally spaced grid, which the shape index needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GridSample:
    """Down-sampled heights on a square grid.

    Attributes
    ----------
    heights : (my, mx) array
        Mean height per cell, metres; NaN for cells no valid point fell in.
    counts : (my, mx) int array
        Number of valid points averaged into each cell.
    x, y : (mx,), (my,) arrays
        Cell-centre coordinates, metres, in the frame of the input's pixel coordinates.
    cell : float
        Cell side, metres.
    """

    heights: FloatArray
    counts: NDArray[np.int64]
    x: FloatArray
    y: FloatArray
    cell: float

    def points(self) -> tuple[FloatArray, NDArray[np.intp]]:
        """Valid cells as ``(m, 3)`` points ``(x, y, z)`` and their flat indices into the grid."""
        flat = np.flatnonzero(np.isfinite(self.heights))
        iy, ix = np.unravel_index(flat, self.heights.shape)
        pts = np.column_stack([self.x[ix], self.y[iy], self.heights.ravel()[flat]])
        return pts, flat


def grid_downsample(
    heights: FloatArray,
    pixel_size: tuple[float, float],
    *,
    cell: float,
    origin: tuple[float, float] = (0.0, 0.0),
    anchor: tuple[float, float] | None = None,
) -> GridSample:
    """Average ``heights`` into square cells of side ``cell``.

    Parameters
    ----------
    heights : (ny, nx) array
        Heights, metres; NaN where missing.
    pixel_size : (dx, dy)
        Pixel pitch, metres.
    cell : float
        Cell side, metres (the paper uses the raster spacing).
    origin : (x0, y0)
        Coordinates of pixel (0, 0), metres.
    anchor : (ax, ay), optional
        A corner of the cell lattice. Defaults to half a pixel before pixel (0, 0), so that a
        cell equal to the pixel size maps pixels one to one. Give a common anchor to put several
        patches on one lattice.

    Returns
    -------
    GridSample
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    dx, dy = float(pixel_size[0]), float(pixel_size[1])
    if dx <= 0 or dy <= 0:
        raise ValueError(f"pixel_size must be positive, got {pixel_size}")
    if not cell > 0:
        raise ValueError(f"cell must be positive, got {cell}")
    if anchor is None:
        anchor = (origin[0] - 0.5 * dx, origin[1] - 0.5 * dy)
    ny, nx = h.shape
    xs = origin[0] + np.arange(nx) * dx
    ys = origin[1] + np.arange(ny) * dy
    # a tiny tolerance keeps pixels that sit exactly on a cell edge in the cell they start
    eps = 1e-9
    ix = np.floor((xs - anchor[0]) / cell + eps).astype(np.int64)
    iy = np.floor((ys - anchor[1]) / cell + eps).astype(np.int64)
    ix0, iy0 = int(ix.min()), int(iy.min())
    mx, my = int(ix.max()) - ix0 + 1, int(iy.max()) - iy0 + 1
    valid = np.isfinite(h)
    flat = ((iy - iy0)[:, None] * mx + (ix - ix0)[None, :])[valid]
    sums = np.bincount(flat, weights=h[valid], minlength=mx * my)
    counts = np.bincount(flat, minlength=mx * my)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    x = anchor[0] + (np.arange(mx) + ix0 + 0.5) * cell
    y = anchor[1] + (np.arange(my) + iy0 + 0.5) * cell
    return GridSample(
        heights=mean.reshape(my, mx),
        counts=counts.reshape(my, mx).astype(np.int64),
        x=np.asarray(x, dtype=np.float64),
        y=np.asarray(y, dtype=np.float64),
        cell=float(cell),
    )
