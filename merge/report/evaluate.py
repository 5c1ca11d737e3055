"""Scoring a mosaic against a reference topography (the truth of a simulation, or a trusted
large scan): how well it is registered, locally and as a whole.

The mosaic's frame may differ from the reference's by one global rigid motion (the gauge of
the merge) and one plane (levelling). Both are fitted first; what is left is the mosaic's own
error. Local misregistration is then measured tile by tile: each tile (e.g. one patch in
size) gets its own best shift (x, y) and Z offset against the reference; their scatter is
the registration error a reader of the map would suffer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Grid:
    """A height map on a regular grid: ``heights`` (ny, nx) metres, pixel (i, j) at
    ``origin + (j * pixel_size[0], i * pixel_size[1])``."""

    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]

    def __post_init__(self) -> None:
        if np.asarray(self.heights).ndim != 2:
            raise ValueError(f"heights must be 2-D, got shape {np.shape(self.heights)}")
        if not all(p > 0 for p in self.pixel_size):
            raise ValueError(f"pixel sizes must be positive, got {self.pixel_size}")


@dataclass(frozen=True)
class Score:
    """Errors in metres.

    shift : global (dx, dy) of the mosaic relative to the reference (the gauge; not an error).
    map_rms : RMS height error after the global fit (shift, offset and plane).
    tile_xy_rms, tile_z_rms : RMS of the per-tile shift (vector length) and Z offset after
        the global fit: the local registration error.
    tile_shifts : (n_tiles, 3) per-tile (dx, dy, dz).
    """

    shift: tuple[float, float]
    map_rms: float
    tile_xy_rms: float
    tile_z_rms: float
    tile_shifts: FloatArray


def _sampler(reference: Grid) -> tuple[FloatArray, tuple[float, float], tuple[float, float]]:
    coeffs = ndimage.spline_filter(np.nan_to_num(reference.heights), order=3)
    return coeffs, reference.origin, reference.pixel_size


def _sample(
    ref: tuple[FloatArray, tuple[float, float], tuple[float, float]], x: FloatArray, y: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Reference heights and gradients (per metre) at (x, y)."""
    coeffs, (ox, oy), (px, py) = ref
    cols, rows = (x - ox) / px, (y - oy) / py
    h = ndimage.map_coordinates(coeffs, [rows, cols], order=3, prefilter=False, mode="nearest")
    e = 0.25
    gx = (
        ndimage.map_coordinates(coeffs, [rows, cols + e], order=3, prefilter=False, mode="nearest")
        - ndimage.map_coordinates(
            coeffs, [rows, cols - e], order=3, prefilter=False, mode="nearest"
        )
    ) / (2 * e * px)
    gy = (
        ndimage.map_coordinates(coeffs, [rows + e, cols], order=3, prefilter=False, mode="nearest")
        - ndimage.map_coordinates(
            coeffs, [rows - e, cols], order=3, prefilter=False, mode="nearest"
        )
    ) / (2 * e * py)
    return h, gx, gy


def _fit(
    ref: tuple[FloatArray, tuple[float, float], tuple[float, float]],
    x: FloatArray,
    y: FloatArray,
    z: FloatArray,
    *,
    start: tuple[float, float],
    plane: bool,
    iterations: int = 12,
) -> tuple[FloatArray, FloatArray]:
    """Gauss-Newton for ``z ≈ ref(x + dx, y + dy) + c (+ a x + b y)``; returns the
    parameters and the residuals."""
    d = np.array(start, dtype=np.float64)
    xc, yc = x - x.mean(), y - y.mean()
    params = np.zeros(5 if plane else 3)
    residual = np.zeros_like(z)
    for _ in range(iterations):
        h, gx, gy = _sample(ref, x + d[0], y + d[1])
        offset = params[2] + (params[3] * xc + params[4] * yc if plane else 0.0)
        residual = z - h - offset
        cols = [gx, gy, np.ones_like(z)] + ([xc, yc] if plane else [])
        jac = np.column_stack(cols)
        scale = np.maximum(np.linalg.norm(jac, axis=0), 1e-30)
        step, *_ = np.linalg.lstsq(jac / scale, residual, rcond=None)
        step /= scale
        d += step[:2]
        params[2:] += step[2:]
        params[:2] = d
        if np.hypot(*step[:2]) < 1e-13:
            break
    h, _, _ = _sample(ref, x + d[0], y + d[1])
    offset = params[2] + (params[3] * xc + params[4] * yc if plane else 0.0)
    return params, z - h - offset


def score_mosaic(
    mosaic: Grid, reference: Grid, *, tile: tuple[float, float], max_shift: float = 200e-9
) -> Score:
    """Score ``mosaic`` against ``reference`` (which must cover it plus ``max_shift``).

    Parameters
    ----------
    mosaic, reference : Grid
    tile : (width, height) metres
        Size of the tiles of the local registration measure (a patch, say).
    max_shift : float
        Largest global offset searched, metres.
    """
    if not (tile[0] > 0 and tile[1] > 0):
        raise ValueError(f"tile sizes must be positive, got {tile}")
    ny, nx = mosaic.heights.shape
    jj, ii = np.meshgrid(np.arange(nx, dtype=np.float64), np.arange(ny, dtype=np.float64))
    x = np.asarray(mosaic.origin[0] + jj * mosaic.pixel_size[0], dtype=np.float64)
    y = np.asarray(mosaic.origin[1] + ii * mosaic.pixel_size[1], dtype=np.float64)
    z = np.asarray(mosaic.heights, dtype=np.float64)
    valid = np.isfinite(z)
    if valid.sum() < 16:
        raise ValueError("the mosaic has fewer than 16 finite heights")
    ref = _sampler(reference)
    xv, yv, zv = x[valid], y[valid], z[valid]
    # coarse global search on a pixel lattice, then Gauss-Newton with a plane
    step = max(max(reference.pixel_size), max_shift / 5)  # Gauss-Newton takes it from there
    n = int(np.ceil(max_shift / step))
    sub = slice(None, None, max(1, zv.size // 5000))
    best, start = np.inf, (0.0, 0.0)
    for sx in range(-n, n + 1):
        for sy in range(-n, n + 1):
            h, _, _ = _sample(ref, xv[sub] + sx * step, yv[sub] + sy * step)
            r = zv[sub] - h
            cost = float(np.var(r))
            if cost < best:
                best, start = cost, (sx * step, sy * step)
    params, residual = _fit(ref, xv, yv, zv, start=start, plane=True)
    shift = (float(params[0]), float(params[1]))
    # remove the global plane from the mosaic, then fit each tile's own shift and offset
    plane = params[2] + params[3] * (xv - xv.mean()) + params[4] * (yv - yv.mean())
    levelled = zv - plane
    tw = max(2, round(tile[0] / mosaic.pixel_size[0]))
    th = max(2, round(tile[1] / mosaic.pixel_size[1]))
    flat = np.full(z.shape, np.nan)
    flat[valid] = levelled
    shifts = []
    for r0 in range(0, ny - th // 2, th):
        for c0 in range(0, nx - tw // 2, tw):
            block = flat[r0 : r0 + th, c0 : c0 + tw]
            ok = np.isfinite(block)
            if ok.mean() < 0.8:
                continue
            bx = x[r0 : r0 + th, c0 : c0 + tw][ok]
            by = y[r0 : r0 + th, c0 : c0 + tw][ok]
            p, _ = _fit(ref, bx, by, block[ok], start=shift, plane=False)
            shifts.append((p[0] - shift[0], p[1] - shift[1], p[2]))
    tiles = np.asarray(shifts, dtype=np.float64).reshape(-1, 3)
    if len(tiles):
        tiles -= tiles.mean(axis=0)  # what one global motion cannot explain
    return Score(
        shift=shift,
        map_rms=float(np.sqrt(np.mean(residual**2))),
        tile_xy_rms=float(np.sqrt(np.mean(tiles[:, 0] ** 2 + tiles[:, 1] ** 2)))
        if len(tiles)
        else float("nan"),
        tile_z_rms=float(np.sqrt(np.mean(tiles[:, 2] ** 2))) if len(tiles) else float("nan"),
        tile_shifts=tiles,
    )
