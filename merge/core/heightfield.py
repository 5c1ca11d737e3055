"""Height maps as continuous surfaces: NaN-aware smoothing, upsampling and bilinear look-up."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]


#: How smoothing continues heights beyond a patch's border (see :func:`smooth_nan`).
Border = Literal["repeat", "mirror"]


def smooth_nan(
    heights: FloatArray, sigma: float | tuple[float, float], *, border: Border = "repeat"
) -> FloatArray:
    """Gaussian smoothing (``sigma`` in pixels, or (rows, columns) apart) that ignores NaN and
    keeps them NaN.

    ``border`` says how the heights continue beyond the patch. ``"repeat"`` repeats the border
    value, which bends a slope that crosses the border by a good fraction of slope x sigma (on a
    grating's flank, nanometres at two pixels). ``"mirror"`` continues point-symmetrically
    (``2 h_0 - h_k``), which keeps the slope but doubles the border pixel's noise into the
    continuation: the better choice where the smoothing is wide and the bias large.
    """
    h = np.asarray(heights, dtype=np.float64)
    widest = float(np.max(sigma))
    if widest <= 0:
        return h.copy()
    pad = int(np.ceil(4.0 * widest)) + 1  # the filter's reach (it truncates at 4 sigma)
    padded = border == "mirror" and min(h.shape) > pad
    if padded:
        h = np.pad(h, pad, mode="reflect", reflect_type="odd")
    ok = np.isfinite(h)
    num = ndimage.gaussian_filter(np.where(ok, h, 0.0), sigma, mode="nearest")
    den = ndimage.gaussian_filter(ok.astype(np.float64), sigma, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = np.where(ok & (den > 1e-6), num / den, np.nan)
    return out[pad:-pad, pad:-pad] if padded else out


#: Pixels of point-symmetric continuation before the spline prefilter: the prefilter's reach
#: (its influence falls by 2 - √3 ≈ 0.27 per pixel, so to 0.5 % over four).
SPLINE_PAD = 4


def upsample2(values: FloatArray, *, margin: int = 0) -> FloatArray:
    """Cubic B-spline interpolation of ``values`` (..., ny, nx) at every half pixel.

    Returns (..., 2 (ny + 2 margin) - 1, 2 (nx + 2 margin) - 1): node ``(2 i, 2 j)`` is pixel
    ``(i - margin, j - margin)``, the others lie halfway between; ``margin`` pixels beyond every
    border are included. Beyond the border the values continue point-symmetrically
    (``2 h_0 - h_k``, which keeps slopes). Where the spline's support (the pixels within one of
    a node, both sides of a half node) holds a NaN, the result is NaN; holes are filled with
    their nearest value before the prefilter, so their influence ends there.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.ndim < 2 or min(a.shape[-2:]) < 2:
        raise ValueError(f"need at least 2 x 2 values, got shape {a.shape}")
    if not 0 <= margin < SPLINE_PAD:
        raise ValueError(f"margin must be 0 to {SPLINE_PAD - 1} pixels, got {margin}")
    # the best plane goes through exactly (only what departs from it meets the border guess)
    ny, nx = a.shape[-2:]
    plane = _best_plane(a)
    a = a - plane(np.arange(ny, dtype=np.float64), np.arange(nx, dtype=np.float64))
    bad = ~np.isfinite(a)
    if bad.any():
        for k in np.ndindex(a.shape[:-2]):
            if bad[k].all():
                a[k] = 0.0
            elif bad[k].any():
                idx = ndimage.distance_transform_edt(
                    bad[k], return_distances=False, return_indices=True
                )
                a[k] = a[k][tuple(idx)]
    pad = [(0, 0)] * (a.ndim - 2) + [(SPLINE_PAD, SPLINE_PAD)] * 2
    c = np.pad(a, pad, mode="reflect", reflect_type="odd")
    for axis in (-1, -2):
        c = ndimage.spline_filter1d(c, order=3, axis=axis, mode="mirror")
    p = SPLINE_PAD - margin
    for axis in (-1, -2):
        n = c.shape[axis] - 2 * p
        # the spline at a node: (1, 4, 1) / 6 of the coefficients; halfway: (1, 23, 23, 1) / 48
        at = ndimage.correlate1d(c, _AT_NODE, axis=axis, mode="nearest")
        half = ndimage.correlate1d(c, _HALFWAY, axis=axis, mode="nearest")
        shape = list(c.shape)
        shape[axis] = 2 * n - 1
        fine = np.empty(shape)
        _along(fine, axis, slice(0, None, 2))[...] = _along(at, axis, slice(p, p + n))
        _along(fine, axis, slice(1, None, 2))[...] = _along(half, axis, slice(p + 1, p + n))
        c = fine
    if bad.any():
        near = ndimage.binary_dilation(bad, structure=_square(a.ndim))
        if margin:
            near = np.pad(near, [(0, 0)] * (a.ndim - 2) + [(margin, margin)] * 2)
        fine_bad = np.zeros(c.shape, dtype=bool)
        fine_bad[..., 0::2, 0::2] = near
        fine_bad[..., 1::2, :] |= _either(fine_bad[..., 0::2, :], axis=-2)
        fine_bad[..., :, 1::2] |= _either(fine_bad[..., :, 0::2], axis=-1)
        c[fine_bad] = np.nan
    rows = np.arange(2 * (ny + 2 * margin) - 1) / 2.0 - margin
    cols = np.arange(2 * (nx + 2 * margin) - 1) / 2.0 - margin
    out: FloatArray = c + plane(rows, cols)
    return out


_AT_NODE = np.array([1.0, 4.0, 1.0]) / 6.0
_HALFWAY = np.array([1.0, 23.0, 23.0, 1.0]) / 48.0  # centred on its third tap: c[i-1] + 23 c[i] ...


def _along(a: FloatArray, axis: int, index: slice) -> FloatArray:
    """The view ``a[..., index, ...]`` with ``index`` on ``axis``."""
    key: list[slice] = [slice(None)] * a.ndim
    key[axis] = index
    out: FloatArray = a[tuple(key)]
    return out


def _best_plane(a: FloatArray) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """Least-squares plane ``c + b_x j + b_y i`` of every 2-D slice of ``a`` over its finite
    values, as a function of rows ``i`` and columns ``j`` (broadcast over the slices)."""
    ny, nx = a.shape[-2:]
    ok = np.isfinite(a)
    if ok.all():
        # a full grid: rows and columns are orthogonal, each slope from its axis's means
        di, dj = np.arange(ny) - 0.5 * (ny - 1), np.arange(nx) - 0.5 * (nx - 1)
        ci, cj = np.full(a.shape[:-2], 0.5 * (ny - 1)), np.full(a.shape[:-2], 0.5 * (nx - 1))
        return _plane_function(
            a.mean(axis=(-2, -1)),
            a.mean(axis=-1) @ di / (di @ di),
            a.mean(axis=-2) @ dj / (dj @ dj),
            ci,
            cj,
        )
    z = np.where(ok, a, 0.0)
    ii, jj = np.meshgrid(
        np.arange(ny, dtype=np.float64), np.arange(nx, dtype=np.float64), indexing="ij"
    )
    n = ok.sum(axis=(-2, -1)).astype(np.float64)
    safe = np.maximum(n, 1.0)
    mi, mj = (ok * ii).sum(axis=(-2, -1)) / safe, (ok * jj).sum(axis=(-2, -1)) / safe
    mz = z.sum(axis=(-2, -1)) / safe
    di, dj = ii - mi[..., None, None], jj - mj[..., None, None]
    sii, sjj, sij = (
        (ok * di * di).sum(axis=(-2, -1)),
        (ok * dj * dj).sum(axis=(-2, -1)),
        (ok * di * dj).sum(axis=(-2, -1)),
    )
    siz, sjz = (ok * di * z).sum(axis=(-2, -1)), (ok * dj * z).sum(axis=(-2, -1))
    det = sii * sjj - sij**2
    good = det > 1e-12 * np.maximum(sii * sjj, 1e-300)
    det = np.where(good, det, 1.0)
    bi = np.where(good, (siz * sjj - sjz * sij) / det, 0.0)
    bj = np.where(good, (sjz * sii - siz * sij) / det, 0.0)
    return _plane_function(mz, bi, bj, mi, mj)


def _plane_function(
    mz: FloatArray, bi: FloatArray, bj: FloatArray, mi: FloatArray, mj: FloatArray
) -> Callable[[FloatArray, FloatArray], FloatArray]:
    """``(i, j) -> mz + bi (i - mi) + bj (j - mj)`` per slice (all arrays of the slices' shape)."""

    def plane(i: FloatArray, j: FloatArray) -> FloatArray:
        e = (...,) + (None, None)
        out: FloatArray = mz[e] + bi[e] * (i[:, None] - mi[e]) + bj[e] * (j[None, :] - mj[e])
        return out

    return plane


@functools.cache
def slope_noise(nodes: int) -> float:
    """Variance (per axis, in units of σ² / pixel²) of the slope of unit white noise looked up as
    :class:`merge.refine.bank.SurfaceBank` does: central differences, interpolated between ``nodes``
    nodes per pixel (1: the pixels, bilinear; 2: :func:`upsample2`, then bilinear), averaged over
    where in a pixel the look-up falls. Bilinear: 1/3 across, 2/3 along, 2/9 in all.
    """
    if nodes not in (1, 2):
        raise ValueError(f"nodes per pixel must be 1 or 2, got {nodes}")
    size, centre = 15, 7
    impulses: FloatArray = np.zeros((size, 2, size))
    impulses[np.arange(size), :, np.arange(size)] = 1.0  # one unit pixel per row pair
    diffs: FloatArray = np.asarray(np.gradient(impulses, axis=-1), dtype=np.float64)
    if nodes > 1:
        impulses, diffs = upsample2(impulses), upsample2(diffs)
    # look-ups at evenly spread places within the centre pixel, bilinear between nodes
    u = (centre + (np.arange(64) + 0.5) / 64) * nodes
    j0 = np.floor(u).astype(np.intp)
    f = u - j0

    def mean_square(w: FloatArray) -> float:
        # w (pixels, 2, nodes): every pixel's weight on every node (twice, a 2-D array's rows);
        # a look-up's weights, squared
        at = (1.0 - f) * w[:, 0, j0] + f * w[:, 0, j0 + 1]
        return float(np.mean(np.sum(at**2, axis=0)))

    return mean_square(diffs) * mean_square(impulses)


def _square(ndim: int) -> NDArray[np.bool_]:
    """3 x 3 neighbourhood over the last two of ``ndim`` axes."""
    out = np.zeros((1,) * (ndim - 2) + (3, 3), dtype=bool)
    out[...] = True
    return out


def _either(mask: NDArray[np.bool_], *, axis: int) -> NDArray[np.bool_]:
    """``mask[k] | mask[k + 1]`` along ``axis``."""
    m = np.moveaxis(mask, axis, 0)
    out: NDArray[np.bool_] = np.moveaxis(m[:-1] | m[1:], 0, axis)
    return out


@dataclass(frozen=True)
class Cells:
    """The bilinear cell of every point at fractional (row ``v``, column ``u``) indices of a
    grid: its lower-left node (``row``, ``col``), how far towards the next row and column
    (``fv``, ``fu``, in [0, 1]) and whether the point lies on the grid (``inside``).
    """

    row: NDArray[np.intp]
    col: NDArray[np.intp]
    fv: FloatArray
    fu: FloatArray
    inside: NDArray[np.bool_]

    @classmethod
    def of(cls, shape: tuple[int, int], v: FloatArray, u: FloatArray) -> Cells:
        """The cells of points ``(v, u)`` (m,) on a grid of ``shape`` (rows, columns)."""
        ny, nx = shape
        eps = 1e-6  # pixels: a node that rounding puts a hair outside the last pixel is inside
        inside = (u >= -eps) & (u <= nx - 1 + eps) & (v >= -eps) & (v <= ny - 1 + eps)
        row = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        col = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        return cls(row, col, np.clip(v - row, 0.0, 1.0), np.clip(u - col, 0.0, 1.0), inside)

    @functools.cached_property
    def weights(self) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """The four nodes' weights (m,) each: lower-left, lower-right, upper-left, upper-right;
        worked out once for every array looked up at the same points."""
        fv, fu = self.fv, self.fu
        return (1 - fv) * (1 - fu), (1 - fv) * fu, fv * (1 - fu), fv * fu

    def values(self, a: FloatArray) -> FloatArray:
        """Bilinear values of ``a`` (the grid's shape) at the points."""
        nx = a.shape[1]
        f = a.ravel()
        flat = self.row * nx + self.col
        w00, w01, w10, w11 = self.weights
        out: FloatArray = (
            w00 * f[flat] + w01 * f[flat + 1] + w10 * f[flat + nx] + w11 * f[flat + nx + 1]
        )
        return out


def bilinear(
    arrays: Sequence[FloatArray], v: FloatArray, u: FloatArray
) -> tuple[list[FloatArray], NDArray[np.bool_]]:
    """Bilinear values of same-shape arrays at fractional (row ``v``, column ``u``) indices.

    Returns the interpolated values and a mask of points inside the grid whose four neighbours
    are all finite in every array. Values outside the mask are meaningless.
    """
    cells = Cells.of(arrays[0].shape, v, u)
    out = [cells.values(a) for a in arrays]
    valid = cells.inside
    for val in out:
        valid = valid & np.isfinite(val)
    return out, valid
