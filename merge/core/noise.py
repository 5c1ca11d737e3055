"""Robust estimate of the white height noise of a scan, and of a patch set."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from merge.core.progress import checkpoint

FloatArray = NDArray[np.float64]

# 1 / (Φ^-1(3/4) * sqrt(6)): the MAD of a second difference of unit white noise is
# 0.6745 * sqrt(6), because the kernel (1, -2, 1) has a squared norm of 6.
_SECOND_DIFF_MAD_TO_SIGMA = 1.0 / (0.6744897501960817 * np.sqrt(6.0))


def estimate_noise(heights: FloatArray) -> float:
    """Standard deviation of white noise in ``heights`` (same unit), from second differences.

    Second differences along the fast axis (columns) cancel offsets and slopes; their median
    absolute value is insensitive to the few large values at edges and steps. Returns 0 for a
    noise-free surface and NaN if fewer than 3 valid columns exist.
    """
    h = np.asarray(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    if h.shape[1] < 3:
        return float("nan")
    d2 = h[:, 2:] - 2.0 * h[:, 1:-1] + h[:, :-2]
    d2 = d2[np.isfinite(d2)]
    if d2.size == 0:
        return float("nan")
    return float(np.median(np.abs(d2)) * _SECOND_DIFF_MAD_TO_SIGMA)


def patch_noise(each: Iterable[float], scale: float) -> float:
    """Median of the patches' noise (metres: :func:`estimate_noise`, as
    :attr:`merge.core.patchset.Patch.noise` keeps it), in units of ``scale`` (metres, the
    typical pixel); a thousandth of it where nothing could be estimated."""
    values = []
    for value in each:
        checkpoint()  # estimated as they are asked for, 10,000 patches take a second
        values.append(value)
    noise = float(np.nanmedian(values)) / scale
    return noise if np.isfinite(noise) and noise > 0 else 1e-3
