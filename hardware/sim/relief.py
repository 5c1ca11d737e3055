"""How steep and how tall a simulated sample is where it is scanned: what the planner's scan
envelope (:mod:`hardware.envelope`) needs to know of it, measured on the surface itself."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from hardware.sim.surfaces import Surface

#: Pitch (m) and side (m) of the grid the slopes are measured on, and the margin on the
#: steepest slope seen there (a larger area may hold a steeper one).
SLOPE_PITCH, SLOPE_SIDE, SLOPE_MARGIN = 4e-9, 4e-6, 1.25
#: Pitch (m) and side (m) of the grid the relief is measured on.
RELIEF_PITCH, RELIEF_SIDE = 20e-9, 8e-6


def _grid(surface: Surface, centre: tuple[float, float], side: float, pitch: float) -> np.ndarray:
    n = round(side / pitch)
    axis = np.arange(n) * pitch - side / 2
    xx, yy = np.meshgrid(centre[0] + axis, centre[1] + axis)
    return np.asarray(surface.height(xx, yy), dtype=np.float64)


def steepest_slope(surface: Surface, *, centre: tuple[float, float] = (0.0, 0.0)) -> float:
    """The steepest rising slope along x (the fast scan axis) on a 4 µm square around
    ``centre``, with a margin for what a larger area may hold."""
    h = _grid(surface, centre, SLOPE_SIDE, SLOPE_PITCH)
    rise = np.diff(h, axis=1) / SLOPE_PITCH
    return float(SLOPE_MARGIN * np.nanmax(np.abs(rise)))


def patch_relief(
    surface: Surface, patch: float, *, centre: tuple[float, float] = (0.0, 0.0)
) -> float:
    """The largest height range (m) within a ``patch``-wide square on an 8 µm square around
    ``centre``."""
    h = _grid(surface, centre, RELIEF_SIDE, RELIEF_PITCH)
    h = np.where(np.isfinite(h), h, np.nanmedian(h))
    size = max(2, round(patch / RELIEF_PITCH))
    span = ndimage.maximum_filter(h, size=size) - ndimage.minimum_filter(h, size=size)
    return float(span.max())
