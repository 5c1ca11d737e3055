"""Koenderink's shape index of a height map on an equally spaced grid.

Decisions the paper leaves open, taken here:

* **Range and sign.** ``SI = (2/π) · arctan((k1 + k2) / (k2 - k1))`` with principal curvatures
  ``k1 >= k2`` of the surface ``z = h(x, y)`` with its normal pointing up (+z). SI lies in
  [-1, 1]: cup -1, valley (rut) -0.5, saddle 0, ridge +0.5, cap (dome) +1 — the convention of
  scikit-image. With this range the paper's weight ``1 - MAD(SI)`` lies in [0, 1].
* **Curvatures with slopes.** The mean and Gaussian curvatures use the full expressions with the
  first derivatives, so the steep walls of a calibration grating get their true curvature rather
  than that of the unrolled Hessian.
* **Smoothing.** Derivatives come from Gaussian derivative filters of width ``smooth`` cells
  (default 1), which keeps the second derivatives of ~1 nm noise from dominating; ``smooth=0``
  uses plain central differences.
* **Flat areas.** Where the curvedness ``sqrt((k1² + k2²) / 2)`` is below a threshold, SI is
  undefined and set to 0, the value of the symmetric saddle: two flat points then agree fully
  (weight 1, they constrain Z well) and a flat point disagrees with a cap or cup by 1. The
  default threshold is three times the curvedness that the grid's own white noise produces after
  the smoothing, so noise on a flat plateau never passes for shape.
* **Missing points.** NaN cells are filled from their nearest valid neighbour for filtering and
  get NaN back in the output.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from merge.core.noise import estimate_noise

FloatArray = NDArray[np.float64]


def principal_curvatures(
    heights: FloatArray, spacing: float, *, smooth: float = 1.0
) -> tuple[FloatArray, FloatArray]:
    """Principal curvatures ``k1 >= k2`` (1/m) of ``z = h(x, y)`` with the normal up.

    Parameters
    ----------
    heights : (ny, nx) array
        Heights on a square grid, metres; no NaN (fill them first).
    spacing : float
        Grid spacing, metres.
    smooth : float, keyword-only
        Gaussian derivative scale in cells; 0 for central differences.
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    if smooth < 0:
        raise ValueError(f"smooth must be >= 0, got {smooth}")
    if smooth > 0:

        def d(order: tuple[int, int]) -> FloatArray:
            out: FloatArray = ndimage.gaussian_filter(h, smooth, order=order, mode="nearest")
            return out

        hy, hx = d((1, 0)) / spacing, d((0, 1)) / spacing
        hyy, hxx, hxy = (
            d((2, 0)) / spacing**2,
            d((0, 2)) / spacing**2,
            d((1, 1)) / spacing**2,
        )
    else:
        hy, hx = (np.asarray(v, dtype=np.float64) for v in np.gradient(h, spacing))
        hyy, hyx = (np.asarray(v, dtype=np.float64) for v in np.gradient(hy, spacing))
        hxy_, hxx = (np.asarray(v, dtype=np.float64) for v in np.gradient(hx, spacing))
        hxy = 0.5 * (hyx + hxy_)
    g2 = 1.0 + hx**2 + hy**2
    gauss = (hxx * hyy - hxy**2) / g2**2
    mean = ((1.0 + hy**2) * hxx - 2.0 * hx * hy * hxy + (1.0 + hx**2) * hyy) / (2.0 * g2**1.5)
    root = np.sqrt(np.maximum(mean**2 - gauss, 0.0))
    return mean + root, mean - root


@lru_cache(maxsize=16)
def _unit_noise_curvedness(smooth: float) -> float:
    """Median curvedness that unit white noise on a unit grid shows after the smoothing."""
    rng = np.random.default_rng(12345)
    noise = rng.standard_normal((96, 96)) * 1e-3  # small: slopes stay in the linear regime
    k1, k2 = principal_curvatures(noise, 1.0, smooth=smooth)
    c = np.sqrt(0.5 * (k1**2 + k2**2))[8:-8, 8:-8]
    return float(np.median(c) / 1e-3)


def shape_index(
    heights: FloatArray,
    spacing: float,
    *,
    smooth: float = 1.0,
    flat_curvedness: float | None = None,
    noise: float | None = None,
) -> FloatArray:
    """Shape index in [-1, 1] of every grid point (see the module notes for the conventions).

    Parameters
    ----------
    heights : (ny, nx) array
        Heights on a square grid, metres; NaN where missing.
    spacing : float
        Grid spacing, metres.
    smooth : float, keyword-only
        Gaussian derivative scale in cells (default 1).
    flat_curvedness : float, optional
        Curvedness (1/m) below which a point is flat (SI = 0). Defaults to three times the
        curvedness of the noise, see ``noise``.
    noise : float, optional
        White-noise standard deviation of ``heights`` (metres); estimated when not given.

    Returns
    -------
    (ny, nx) array
        SI per point; NaN where the input is NaN.
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    valid = np.isfinite(h)
    if not valid.any():
        return np.full(h.shape, np.nan)
    if not valid.all():
        idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        h = h[tuple(idx)]
    k1, k2 = principal_curvatures(h, spacing, smooth=smooth)
    if flat_curvedness is None:
        sigma = estimate_noise(np.where(valid, h, np.nan)) if noise is None else noise
        if not np.isfinite(sigma):
            sigma = 0.0
        flat_curvedness = 3.0 * sigma * _unit_noise_curvedness(float(smooth)) / spacing**2
    curvedness = np.sqrt(0.5 * (k1**2 + k2**2))
    si = -(2.0 / np.pi) * np.arctan2(k1 + k2, k1 - k2)
    si = np.where(curvedness > flat_curvedness, si, 0.0)
    si[~valid] = np.nan
    out: FloatArray = si
    return out
