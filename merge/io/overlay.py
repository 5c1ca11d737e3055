"""A topography over the SEM image it was registered on (:mod:`merge.correlative`): the SEM's
grey levels around the mosaic, the heights in the AFM colour map blended over them where the
registration puts them. Pure: arrays in, an RGB picture out."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from merge.correlative import SEMView, Similarity
from merge.io.preview import afm_colors

FloatArray = NDArray[np.float64]
UInt8Array = NDArray[np.uint8]


def heights_on_sem(
    heights: FloatArray,
    sem: SEMView,
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    transform: Similarity,
    box: tuple[int, int, int, int] | None = None,
) -> FloatArray:
    """The heights resampled on the SEM image's pixels (bilinear; NaN where the mosaic does
    not reach), the mosaic placed where ``transform`` (``T_sem_mosaic``) puts it. ``box``:
    columns and rows ``(c0, r0, columns, rows)`` of the SEM image to fill (default: all)."""
    h = np.asarray(heights, dtype=np.float64)
    rows_n, cols_n = np.asarray(sem.pixels).shape
    c0, r0, nc, nr = box if box is not None else (0, 0, cols_n, rows_n)
    cols, rows = np.meshgrid(
        c0 + np.arange(nc, dtype=np.float64), r0 + np.arange(nr, dtype=np.float64)
    )
    mosaic = transform.invert(sem.to_stage(cols, rows))
    i = (mosaic[..., 1] - origin[1]) / pixel_size[1]
    j = (mosaic[..., 0] - origin[0]) / pixel_size[0]
    ny, nx = h.shape
    inside = (i >= 0) & (i <= ny - 1) & (j >= 0) & (j <= nx - 1)
    valid = np.isfinite(h)
    filled = np.where(valid, h, 0.0)
    ii, jj = np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1)
    out: FloatArray = ndimage.map_coordinates(filled, [ii, jj], order=1)
    measured = ndimage.map_coordinates(valid.astype(np.float64), [ii, jj], order=0) > 0.5
    out[~(inside & measured)] = np.nan
    return out


def footprint_box(
    sem: SEMView,
    corners: FloatArray,
    transform: Similarity,
    *,
    margin: float = 0.15,
) -> tuple[int, int, int, int]:
    """The SEM pixels around where ``transform`` puts the mosaic's ``corners`` (4, 2 stage
    metres), widened by ``margin`` of its size each way and clipped to the image."""
    seen = sem.to_pixel(transform.apply(corners))
    lo, hi = seen.min(axis=0), seen.max(axis=0)
    pad = margin * float((hi - lo).max())
    rows_n, cols_n = np.asarray(sem.pixels).shape
    c0, r0 = max(0, int(lo[0] - pad)), max(0, int(lo[1] - pad))
    c1, r1 = min(cols_n, int(hi[0] + pad) + 1), min(rows_n, int(hi[1] + pad) + 1)
    if c1 - c0 < 2 or r1 - r0 < 2:
        raise ValueError("the mosaic lies outside the SEM image")
    return c0, r0, c1 - c0, r1 - r0


def mosaic_corners(
    shape: tuple[int, int], origin: tuple[float, float], pixel_size: tuple[float, float]
) -> FloatArray:
    """The (4, 2) stage points of a mosaic's corner pixels: ``shape`` (rows, columns) from
    ``origin``, rows along +y."""
    ny, nx = shape
    out: FloatArray = np.asarray(origin) + np.array(
        [[0, 0], [nx - 1, 0], [0, ny - 1], [nx - 1, ny - 1]]
    ) * np.asarray(pixel_size)
    return out


def overlay_frame(
    sem: SEMView,
    corners: FloatArray,
    transform: Similarity,
    *,
    margin: float = 0.15,
) -> tuple[tuple[int, int, int, int], FloatArray]:
    """What :func:`overlay_rgb` shows: its box of SEM pixels (:func:`footprint_box`) and the
    (2, 3) affine map from its pixels ``(column, row, 1)`` (row 0 its top line) to mosaic
    coordinates (stage metres), for a profile drawn on it."""
    box = footprint_box(sem, corners, transform, margin=margin)
    c0, r0 = box[0], box[1]
    probe = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    at = transform.invert(sem.to_stage(c0 + probe[:, 0], r0 + probe[:, 1]))
    out: FloatArray = np.column_stack([at[1] - at[0], at[2] - at[0], at[0]])
    return box, out


def overlay_rgb(
    heights: FloatArray,
    sem: SEMView,
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    transform: Similarity,
    opacity: float = 0.5,
    margin: float = 0.15,
) -> UInt8Array:
    """The SEM image around the mosaic in grey (1-99 % stretched), the heights in the AFM
    colour map blended over it with ``opacity`` (0: the SEM alone, 1: the heights alone)
    where the mosaic lies. Returns ``(rows, columns, 3)`` uint8, row 0 the SEM's top line."""
    if not 0.0 <= opacity <= 1.0:
        raise ValueError(f"opacity must be in 0..1, got {opacity}")
    h = np.asarray(heights, dtype=np.float64)
    corners = mosaic_corners(h.shape, origin, pixel_size)
    box = footprint_box(sem, corners, transform, margin=margin)
    c0, r0, nc, nr = box
    grey = np.asarray(sem.pixels, dtype=np.float64)[r0 : r0 + nr, c0 : c0 + nc]
    lo, hi = np.percentile(grey, [1, 99])
    grey01 = np.clip((grey - lo) / max(hi - lo, 1e-300), 0.0, 1.0)
    out = np.repeat(grey01[..., None], 3, axis=-1) * 255.0
    placed = heights_on_sem(
        h, sem, origin=origin, pixel_size=pixel_size, transform=transform, box=box
    )
    covered = np.isfinite(placed)
    if covered.any():
        z_lo, z_hi = np.percentile(placed[covered], [1, 99])
        colours = afm_colors((placed - z_lo) / max(z_hi - z_lo, 1e-300)).astype(np.float64)
        out[covered] = (1 - opacity) * out[covered] + opacity * colours[covered]
    result: UInt8Array = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    return result


def sem_on_mosaic(
    sem: SEMView,
    shape: tuple[int, int],
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    transform: Similarity,
) -> FloatArray:
    """The SEM image resampled on the mosaic's grid (``shape`` rows along +y from
    ``origin``; bilinear, NaN where the image does not reach): each mosaic point takes the
    SEM's signal where ``transform`` (``T_sem_mosaic``) says the image shows it."""
    ny, nx = shape
    cols, rows = np.meshgrid(np.arange(nx, dtype=np.float64), np.arange(ny, dtype=np.float64))
    points = np.stack([origin[0] + cols * pixel_size[0], origin[1] + rows * pixel_size[1]], -1)
    at = sem.to_pixel(transform.apply(points))
    image = np.asarray(sem.pixels, dtype=np.float64)
    rows_n, cols_n = image.shape
    inside = (at[..., 0] >= 0) & (at[..., 0] <= cols_n - 1)
    inside &= (at[..., 1] >= 0) & (at[..., 1] <= rows_n - 1)
    out: FloatArray = ndimage.map_coordinates(
        image, [np.clip(at[..., 1], 0, rows_n - 1), np.clip(at[..., 0], 0, cols_n - 1)], order=1
    )
    out[~inside] = np.nan
    return out


def profile(
    heights: FloatArray,
    sem: SEMView,
    start: tuple[float, float],
    end: tuple[float, float],
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    transform: Similarity,
    samples: int = 256,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The heights and the SEM signal along the segment from ``start`` to ``end`` (mosaic
    coordinates, stage metres), ``samples`` points: distance along it (metres), heights
    (metres) and SEM signal, bilinear, NaN where either does not reach."""
    if not 2 <= samples <= 100_000:
        raise ValueError(f"samples must be in 2..100000, got {samples}")
    a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()) or np.allclose(a, b):
        raise ValueError("a profile needs two distinct, finite end points")
    s = np.linspace(0.0, 1.0, samples)
    points = a + s[:, None] * (b - a)
    h = np.asarray(heights, dtype=np.float64)
    ny, nx = h.shape
    i = (points[:, 1] - origin[1]) / pixel_size[1]
    j = (points[:, 0] - origin[0]) / pixel_size[0]
    inside = (i >= 0) & (i <= ny - 1) & (j >= 0) & (j <= nx - 1)
    valid = np.isfinite(h)
    ii, jj = np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1)
    along: FloatArray = ndimage.map_coordinates(np.where(valid, h, 0.0), [ii, jj], order=1)
    measured = ndimage.map_coordinates(valid.astype(np.float64), [ii, jj], order=0) > 0.5
    along[~(inside & measured)] = np.nan
    at = sem.to_pixel(transform.apply(points))
    image = np.asarray(sem.pixels, dtype=np.float64)
    rows_n, cols_n = image.shape
    seen = (at[:, 0] >= 0) & (at[:, 0] <= cols_n - 1) & (at[:, 1] >= 0) & (at[:, 1] <= rows_n - 1)
    signal: FloatArray = ndimage.map_coordinates(
        image, [np.clip(at[:, 1], 0, rows_n - 1), np.clip(at[:, 0], 0, cols_n - 1)], order=1
    )
    signal[~seen] = np.nan
    distance: FloatArray = s * float(np.hypot(*(b - a)))
    return distance, along, signal
