"""The secondary-electron contrast a topography makes, as an Everhart-Thornley detector sees it.

The SE yield of a surface element grows with its tilt ``θ`` to the beam, about as
``1 / cos θ`` (edges and slopes bright); the side-mounted detector collects more from faces
turned towards it, in proportion to the slope along its direction (shading); convex edges
brighten further, electrons escaping through the side wall too. The SEM sees the
slope over its probe's reach (the ``resolution``), a length no image states: the registration
picks the one that fits. Neither gain nor
the detector's direction is known for an image, so the contrast is returned as features whose
weights a fit finds: ``SE ≈ a0 + a1 (1 / cos θ - 1) + a2 ∂h/∂x + a3 ∂h/∂y + a4 κ``, ``κ``
the convexity (the curvature where the surface bends down).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]

#: The features :func:`se_features` returns, in order.
FEATURES = ("tilt", "slope_x", "slope_y", "convexity")


def se_features(
    heights: FloatArray,
    pixel_size: tuple[float, float],
    *,
    resolution: float = 0.0,
    blur: float = 0.0,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The SE contrast features of a topography and where they are defined.

    Parameters
    ----------
    heights : (ny, nx) array
        Heights, metres; row ``i`` at ``y0 + i * pixel_size[1]`` (rows along +y). NaN where
        nothing was measured.
    pixel_size : (dx, dy)
        Metres.
    resolution : float, keyword-only
        Standard deviation, pixels, of a Gaussian taken over the heights before their slopes:
        the reach of the SEM's probe and interaction volume, over which it sees one slope.
    blur : float, keyword-only
        Standard deviation, pixels, of a Gaussian taken over the features (the yield spread
        over the SE escape range, or anti-aliasing before sampling on a coarser grid).

    Returns
    -------
    features : (4, ny, nx) array
        :data:`FEATURES`: ``1 / cos θ - 1``, the slopes along x and y, and the convexity (its
        curvature times the pixel), all dimensionless.
    valid : (ny, nx) bool array
        Where the heights were measured.
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2 or min(h.shape) < 4:
        raise ValueError(f"heights must be a 2-D array of 4 x 4 at least, got shape {h.shape}")
    dx, dy = (float(v) for v in pixel_size)
    if not (np.isfinite(dx) and np.isfinite(dy) and dx > 0 and dy > 0):
        raise ValueError(f"pixel_size must be two positive lengths, got {pixel_size}")
    if not (np.isfinite(blur) and blur >= 0 and np.isfinite(resolution) and resolution >= 0):
        raise ValueError(f"blur and resolution must be non-negative pixels: {blur}, {resolution}")
    valid = np.isfinite(h)
    if not valid.any():
        raise ValueError("the heights hold no measured value")
    filled = np.where(valid, h, float(np.nanmedian(h)))
    if resolution > 0:  # the slopes the SEM sees, over its probe's reach
        filled = ndimage.gaussian_filter(filled, resolution, mode="nearest")
    gy, gx = np.gradient(filled, dy, dx)
    tilt = np.sqrt(1.0 + gx**2 + gy**2) - 1.0  # 1 / cos θ - 1
    # convex edges brighten (electrons escape through the side wall too): the curvature
    # where the surface bends down, over a pixel (dimensionless: heights over the pixel)
    laplacian = np.gradient(gx, dx, axis=1) + np.gradient(gy, dy, axis=0)
    convexity = np.maximum(-laplacian, 0.0) * math.sqrt(dx * dy)
    out = np.stack([tilt, gx, gy, convexity])
    if blur > 0:
        for k in range(len(out)):
            out[k] = ndimage.gaussian_filter(out[k], blur, mode="nearest")
    return out, valid
