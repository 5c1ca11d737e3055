"""Rendering a mosaic: every patch resampled through its transform onto one regular grid.

For every node ``(X, Y)`` of the mosaic grid and every patch that covers it, the patch point whose
transform lands there is found by inverting the transform (:class:`PatchTransform`) with
``p = (x, y, h(x, y))``: its drift plane moves heights only, so XY inverts through the rigid part
(with a few fixed-point rounds on the height when the rotation tilts). The patch is interpolated
bilinearly there (never dropped into the nearest cell), and overlapping patches are blended with
weights that fall smoothly to zero at each patch's border, so no seam is left where registrations
differ by noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.heightfield import bilinear
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class Mosaic:
    """A rendered height map.

    Attributes
    ----------
    heights
        (ny, nx) metres, NaN where no patch covers.
    origin
        (x, y) mosaic-frame position of pixel (0, 0), metres.
    pixel_size
        (dx, dy) metres.
    coverage
        (ny, nx) number of patches that contributed to every pixel.
    """

    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    coverage: NDArray[np.int32]


def _corners(p: Patch) -> FloatArray:
    x0, y0, x1, y1 = p.footprint
    z = p.median_height
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])


def mosaic_bounds(
    patches: Sequence[Patch], transforms: Sequence[PatchTransform]
) -> tuple[float, float, float, float]:
    """``(xmin, ymin, xmax, ymax)`` of all transformed patch outlines, metres."""
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for p, tr in zip(patches, transforms, strict=True):
        checkpoint()
        q = tr.apply(_corners(p))
        lo = np.minimum(lo, q[:, :2].min(axis=0))
        hi = np.maximum(hi, q[:, :2].max(axis=0))
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def render_mosaic(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform] | None = None,
    *,
    pixel_size: tuple[float, float] | None = None,
    bounds: tuple[float, float, float, float] | None = None,
    feather: float = 0.15,
) -> Mosaic:
    """Resample all patches through their transforms onto one grid and blend them.

    Parameters
    ----------
    patches : sequence of Patch
    transforms : sequence of PatchTransform, optional
        ``T_mosaic_patch`` per patch; the nominal placement when not given.
    pixel_size : (dx, dy), keyword-only
        Mosaic pixel pitch, metres; defaults to the finest patch pitch per axis.
    bounds : (xmin, ymin, xmax, ymax), keyword-only
        Area to render; defaults to the union of the transformed patches.
    feather : float, keyword-only
        Width of the blending ramp at each patch border, as a fraction of the patch's smaller
        side (0 for plain averaging).
    """
    n = len(patches)
    trs = list(transforms) if transforms is not None else [PatchTransform() for _ in range(n)]
    if len(trs) != n:
        raise ValueError(f"need one transform per patch: {n} patches, {len(trs)} transforms")
    if not 0 <= feather <= 0.5:
        raise ValueError(f"feather must be in [0, 0.5], got {feather}")
    if pixel_size is None:
        pixel_size = (
            min(p.pixel_size[0] for p in patches),
            min(p.pixel_size[1] for p in patches),
        )
    dx, dy = float(pixel_size[0]), float(pixel_size[1])
    if dx <= 0 or dy <= 0:
        raise ValueError(f"pixel_size must be positive, got {pixel_size}")
    xmin, ymin, xmax, ymax = bounds if bounds is not None else mosaic_bounds(patches, trs)
    nx = int(np.floor((xmax - xmin) / dx + 1e-9)) + 1
    ny = int(np.floor((ymax - ymin) / dy + 1e-9)) + 1
    grid = MosaicGrid(xmin, ymin, dx, dy, nx, ny)
    acc = np.zeros((ny, nx))
    wsum = np.zeros((ny, nx))
    coverage = np.zeros((ny, nx), dtype=np.int32)
    for p, tr in zip(patches, trs, strict=True):
        checkpoint(1)
        hit = resample_patch(p, tr, grid, feather)
        if hit is None:
            continue
        ii, jj, wz, w = hit
        # (ii, jj) are unique within one patch, so plain fancy-index adds are exact
        acc[ii, jj] += wz
        wsum[ii, jj] += w
        coverage[ii, jj] += 1
    # the heights in the sums' own array: a large mosaic is not held twice
    covered = wsum > 0
    np.divide(acc, wsum, out=acc, where=covered)
    del wsum
    acc[~covered] = np.nan
    return Mosaic(heights=acc, origin=(xmin, ymin), pixel_size=(dx, dy), coverage=coverage)


@dataclass(frozen=True)
class MosaicGrid:
    """A mosaic's lattice: node (0, 0) at ``(xmin, ymin)``, pitch ``(dx, dy)`` (metres), ``nx``
    by ``ny`` nodes."""

    xmin: float
    ymin: float
    dx: float
    dy: float
    nx: int
    ny: int


def resample_patch(
    p: Patch, tr: PatchTransform, grid: MosaicGrid, feather: float
) -> tuple[IntArray, IntArray, FloatArray, FloatArray] | None:
    """Patch ``p`` through ``tr`` at the grid nodes it covers: their rows and columns, its
    blending weight times height, and the weight; None where it covers none.

    One patch's share of :func:`render_mosaic`: the sums of the shares of all patches, divided
    by the sums of their weights, are the mosaic (:class:`merge.live.LiveCanvas` keeps them
    and replaces a patch's share when it moves).
    """
    xmin, ymin, dx, dy = grid.xmin, grid.ymin, grid.dx, grid.dy
    R, t = tr.R, tr.t
    zc = p.median_height
    q = tr.apply(_corners(p))
    j0 = max(int(np.floor((q[:, 0].min() - xmin) / dx)) - 1, 0)
    j1 = min(int(np.ceil((q[:, 0].max() - xmin) / dx)) + 1, grid.nx - 1)
    i0 = max(int(np.floor((q[:, 1].min() - ymin) / dy)) - 1, 0)
    i1 = min(int(np.ceil((q[:, 1].max() - ymin) / dy)) + 1, grid.ny - 1)
    if j1 < j0 or i1 < i0:
        return None
    X, Y = np.meshgrid(xmin + np.arange(j0, j1 + 1) * dx, ymin + np.arange(i0, i1 + 1) * dy)
    X, Y = X.ravel(), Y.ravel()
    Ainv = np.linalg.inv(R[:2, :2])
    z = np.full(X.shape, zc)
    valid = np.zeros(X.shape, dtype=bool)
    u = v = np.zeros(X.shape)
    # the drift plane moves Z only, so XY inverts through the rigid part; a tilt (if any)
    # couples XY to the height, hence a few fixed-point rounds
    for _ in range(3 if np.abs(R[:2, 2]).max() > 0 else 1):
        rhs = np.column_stack([X, Y]) - t[:2] - np.outer(z, R[:2, 2])
        xy = rhs @ Ainv.T
        u = (xy[:, 0] - p.origin[0]) / p.pixel_size[0]
        v = (xy[:, 1] - p.origin[1]) / p.pixel_size[1]
        (zi,), valid = bilinear((p.heights,), v, u)
        z = np.where(valid, zi, zc)
    x_p = p.origin[0] + u * p.pixel_size[0]
    y_p = p.origin[1] + v * p.pixel_size[1]
    Z = R[2, 0] * x_p + R[2, 1] * y_p + R[2, 2] * z + t[2]
    Z = Z + (x_p - tr.centre[0]) * tr.slope[0] + (y_p - tr.centre[1]) * tr.slope[1]
    w = np.where(valid, _blend_weight(p, u, v, feather), 0.0)
    ii = (np.repeat(np.arange(i0, i1 + 1), j1 - j0 + 1))[valid]
    jj = (np.tile(np.arange(j0, j1 + 1), i1 - i0 + 1))[valid]
    return ii, jj, (w * Z)[valid], w[valid]


def _blend_weight(p: Patch, u: FloatArray, v: FloatArray, feather: float) -> FloatArray:
    """Blending weights at patch pixel coordinates ``(u, v)``: a smooth step from 1e-3 at the
    border to 1 at ``feather`` of the patch's smaller side in (1 everywhere at 0)."""
    pny, pnx = p.shape
    edge = np.minimum.reduce([u, pnx - 1 - u, v, pny - 1 - v])
    ramp = feather * min(pnx, pny)
    if ramp > 0:
        s = np.clip(edge / ramp, 0.0, 1.0)
        w: FloatArray = 1e-3 + s * s * (3.0 - 2.0 * s)
        return w
    return np.ones_like(edge)
