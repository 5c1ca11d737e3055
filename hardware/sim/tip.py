"""The simulated tip's apex: a sphere riding on the surface, touching it at its highest point
near the apex (the image a perfect AFM records: the surface dilated by the tip)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from hardware.sim.surfaces import Surface

FloatArray = NDArray[np.float64]


def _offsets() -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unit offsets of the apex and 16 points of a spherical tip, and how far each sits above
    the apex when the sphere touches there (in tip radii)."""
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ox = np.concatenate([[0.0], 0.5 * np.cos(ang), np.cos(ang)])
    oy = np.concatenate([[0.0], 0.5 * np.sin(ang), np.sin(ang)])
    lift = 1.0 - np.sqrt(np.maximum(1.0 - ox**2 - oy**2, 0.0))
    return ox, oy, lift


OFFSETS = _offsets()


def apex_height(surface: Surface, x: FloatArray, y: FloatArray, radius: float) -> FloatArray:
    """Where the apex of a sphere of ``radius`` (metres) rides over ``surface`` at ``x``,
    ``y`` (metres, any equal shapes): one surface call for the apex and 16 points around it."""
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ox, oy, lift = OFFSETS
    hx = xa.reshape(-1)[None, :] + radius * ox[:, None]
    hy = ya.reshape(-1)[None, :] + radius * oy[:, None]
    touch = surface.height(hx, hy) - radius * lift[:, None]
    out: FloatArray = np.nanmax(touch, axis=0).reshape(xa.shape)
    return out
