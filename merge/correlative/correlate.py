"""Masked normalised cross-correlation over a window of shifts, by FFT (as Padfield's masked
FFT registration does it): a template known only inside a mask, against an image."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import fft, ndimage

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Peak:
    """The best shift (columns, rows; pixels, sub-pixel), its correlation, and the best
    correlation found at least ``apart`` pixels away from it (a rival: the same match
    elsewhere, as a periodic sample makes). ``ridge``: the rival is joined to the best by a
    ridge of correlation as high as itself nearly all the way (the structure runs one way
    only, a lone edge or parallel lines, and the match slides along it), not a peak apart."""

    columns: float
    rows: float
    score: float
    rival: float
    ridge: bool = False


#: Along a ridge the correlation between the best and its rival stays above this part of the
#: rival's.
RIDGE_LEVEL = 0.9


def masked_ncc(
    template: FloatArray, mask: BoolArray, image: FloatArray, *, radius: int
) -> FloatArray:
    """The normalised cross-correlation of ``template`` (inside ``mask``) with ``image``
    shifted by every ``(rows, columns)`` up to ``radius`` pixels.

    Parameters
    ----------
    template, mask, image : (ny, nx) arrays of one shape
        The mask must lie ``radius`` pixels inside the frame, so that no shift takes it out.
    radius : int

    Returns
    -------
    (2 radius + 1, 2 radius + 1) array
        ``out[radius + dr, radius + dc]``: the correlation with the image's content moved by
        ``(-dc, -dr)``, i.e. the template's feature found ``dc`` columns right, ``dr`` rows
        down in the image. Shifts with too little variance in the image are -1.
    """
    t = np.asarray(template, dtype=np.float64)
    f = np.asarray(image, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if not (t.shape == f.shape == m.shape) or t.ndim != 2:
        raise ValueError(
            f"template, mask and image of one 2-D shape: {t.shape}, {m.shape}, {f.shape}"
        )
    if radius < 0 or 2 * radius + 1 > min(t.shape):
        raise ValueError(f"radius {radius} does not fit a {t.shape} frame")
    rows, cols = np.nonzero(m)
    if len(rows) < 16:
        raise ValueError("the mask holds fewer than 16 pixels")
    ny, nx = t.shape
    if (
        rows.min() < radius
        or cols.min() < radius
        or rows.max() >= ny - radius
        or cols.max() >= nx - radius
    ):
        raise ValueError(f"the mask must lie {radius} px inside the frame")
    w = m.astype(np.float64)
    n = float(w.sum())
    centred = np.where(m, t - t[m].mean(), 0.0)
    energy = float(np.sum(centred**2))
    f = f - float(f.mean())  # a constant out: the sums below lose less to rounding
    # zeros past the frame change no sum over the mask for shifts up to the radius
    shape = (fft.next_fast_len(ny, real=True), fft.next_fast_len(nx, real=True))
    fw, ft = fft.rfft2(w, s=shape, workers=-1), fft.rfft2(centred, s=shape, workers=-1)
    ff, ff2 = fft.rfft2(f, s=shape, workers=-1), fft.rfft2(f * f, s=shape, workers=-1)
    ny, nx = shape

    def lagged(a: NDArray[np.complex128], b: NDArray[np.complex128]) -> FloatArray:
        out: FloatArray = fft.irfft2(np.conj(a) * b, s=shape, workers=-1)
        return out

    s_tf, s_f, s_f2 = lagged(ft, ff), lagged(fw, ff), lagged(fw, ff2)
    lags = np.arange(-radius, radius + 1)
    window = np.ix_(lags % ny, lags % nx)
    variance = s_f2[window] - s_f[window] ** 2 / n
    scale = np.sqrt(np.maximum(energy * variance, 0.0))
    good = scale > 1e-12 * max(float(scale.max()), 1e-300)
    out = np.full(variance.shape, -1.0)
    out[good] = s_tf[window][good] / scale[good]
    return out


def _parabola(a: float, b: float, c: float) -> float:
    d = a - 2 * b + c
    return 0.0 if d >= 0 else 0.5 * (a - c) / d


def best_peak(ncc: FloatArray, *, apart: float) -> Peak:
    """The highest correlation of a :func:`masked_ncc` window (sub-pixel by parabolas), and
    the highest other summit at least ``apart`` pixels from it."""
    radius = ncc.shape[0] // 2
    r, c = (int(v) for v in np.unravel_index(int(np.argmax(ncc)), ncc.shape))
    dr = _parabola(*(float(ncc[r + k, c]) for k in (-1, 0, 1))) if 0 < r < ncc.shape[0] - 1 else 0.0
    dc = _parabola(*(float(ncc[r, c + k]) for k in (-1, 0, 1))) if 0 < c < ncc.shape[1] - 1 else 0.0
    yy, xx = np.mgrid[0 : ncc.shape[0], 0 : ncc.shape[1]]
    far = np.hypot(yy - r, xx - c) >= apart
    summits = far & (ncc >= ndimage.maximum_filter(ncc, size=3, mode="nearest"))
    if not summits.any():
        return Peak(c - radius + dc, r - radius + dr, float(ncc[r, c]), -1.0)
    at = int(np.argmax(np.where(summits, ncc, -np.inf)))
    rr, rc = np.unravel_index(at, ncc.shape)
    rival = float(ncc[rr, rc])
    steps = np.linspace(0.0, 1.0, 2 * int(np.hypot(rr - r, rc - c)) + 2)
    between = ndimage.map_coordinates(ncc, [r + steps * (rr - r), c + steps * (rc - c)], order=1)
    ridge = rival > 0 and bool(between.min() >= RIDGE_LEVEL * rival)
    return Peak(c - radius + dc, r - radius + dr, float(ncc[r, c]), rival, ridge)
