"""Height maps as continuous surfaces: NaN-aware smoothing, slopes and bilinear look-up."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]


def smooth_nan(
    heights: FloatArray, sigma: float, *, border: Literal["repeat", "mirror"] = "repeat"
) -> FloatArray:
    """Gaussian smoothing (``sigma`` in pixels) that ignores NaN and keeps them NaN.

    ``border`` says how the heights continue beyond the patch. ``"repeat"`` repeats the border
    value, which bends a slope that crosses the border by a good fraction of slope x sigma (on a
    grating's flank, nanometres at two pixels). ``"mirror"`` continues point-symmetrically
    (``2 h_0 - h_k``), which keeps the slope but doubles the border pixel's noise into the
    continuation: the better choice where the smoothing is wide and the bias large.
    """
    h = np.asarray(heights, dtype=np.float64)
    if sigma <= 0:
        return h.copy()
    pad = int(np.ceil(4.0 * sigma)) + 1  # the filter's reach (it truncates at 4 sigma)
    padded = border == "mirror" and min(h.shape) > pad
    if padded:
        h = np.pad(h, pad, mode="reflect", reflect_type="odd")
    ok = np.isfinite(h)
    num = ndimage.gaussian_filter(np.where(ok, h, 0.0), sigma, mode="nearest")
    den = ndimage.gaussian_filter(ok.astype(np.float64), sigma, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = np.where(ok & (den > 1e-6), num / den, np.nan)
    return out[pad:-pad, pad:-pad] if padded else out


def slopes(heights: FloatArray, pixel_size: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
    """``(dh/dx, dh/dy)`` by central differences (one-sided at edges); NaN next to holes."""
    h = np.asarray(heights, dtype=np.float64)
    gy, gx = np.gradient(h, pixel_size[1], pixel_size[0])
    return np.asarray(gx, dtype=np.float64), np.asarray(gy, dtype=np.float64)


def bilinear(
    arrays: Sequence[FloatArray], v: FloatArray, u: FloatArray
) -> tuple[list[FloatArray], NDArray[np.bool_]]:
    """Bilinear values of same-shape arrays at fractional (row ``v``, column ``u``) indices.

    Returns the interpolated values and a mask of points inside the grid whose four neighbours
    are all finite in every array. Values outside the mask are meaningless.
    """
    ny, nx = arrays[0].shape
    eps = 1e-6  # pixels: a node that rounding puts a hair outside the last pixel is inside
    inside = (u >= -eps) & (u <= nx - 1 + eps) & (v >= -eps) & (v <= ny - 1 + eps)
    i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
    j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
    fv = np.clip(v - i0, 0.0, 1.0)
    fu = np.clip(u - j0, 0.0, 1.0)
    w00 = (1 - fv) * (1 - fu)
    w01 = (1 - fv) * fu
    w10 = fv * (1 - fu)
    w11 = fv * fu
    flat = i0 * nx + j0
    out = []
    valid = inside
    for a in arrays:
        f = a.ravel()
        val = w00 * f[flat] + w01 * f[flat + 1] + w10 * f[flat + nx] + w11 * f[flat + nx + 1]
        valid = valid & np.isfinite(val)
        out.append(val)
    return out, valid
