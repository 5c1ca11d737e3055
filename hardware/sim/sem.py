"""The simulated SEM: secondary-electron images of the sample with a known calibration.

Contrast, as an Everhart-Thornley detector sees a surface: the secondary-electron yield grows
with the local tilt (about ``1 / cos θ``), so edges and slopes are bright; the side-mounted
detector adds shading (faces turned towards it are brighter); shot noise on top. Pixel
``(col, row)`` of an image lies at stage (sample) position ``origin + (col, row) * pixel``.
"""

from __future__ import annotations

import numpy as np

from hardware.protocols import SEMImage
from hardware.sim.surfaces import Surface


class SimulatedSEM:
    """An SEM looking at ``surface``.

    Parameters
    ----------
    surface : Surface
    noise : float
        Relative shot noise of a pixel.
    detector : (dx, dy)
        Horizontal direction of the secondary-electron detector (unit vector).
    seed : int
    """

    def __init__(
        self,
        surface: Surface,
        *,
        noise: float = 0.05,
        detector: tuple[float, float] = (0.7071, 0.7071),
        seed: int = 0,
    ) -> None:
        self.surface = surface
        self.noise = noise
        self.detector = np.asarray(detector, dtype=np.float64)
        self.rng = np.random.default_rng(seed)

    def grab(self, *, centre: tuple[float, float], field: float, pixels: int) -> SEMImage:
        """An image ``field`` metres wide, ``pixels`` square, centred on ``centre`` (stage)."""
        if not field > 0:
            raise ValueError(f"field must be positive, got {field}")
        if not 8 <= pixels <= 4096:
            raise ValueError(f"pixels must be in 8..4096, got {pixels}")
        pitch = field / pixels
        origin = (centre[0] - field / 2 + pitch / 2, centre[1] - field / 2 + pitch / 2)
        x = origin[0] + np.arange(pixels) * pitch
        y = origin[1] + np.arange(pixels) * pitch
        xx, yy = np.meshgrid(x, y)
        h = self.surface.height(xx, yy)
        h = np.where(np.isfinite(h), h, np.nanmin(h) if np.isfinite(h).any() else 0.0)
        gy, gx = np.gradient(h, pitch)
        cos_tilt = 1.0 / np.sqrt(1.0 + gx**2 + gy**2)
        yield_ = 1.0 / cos_tilt  # tilt contrast: edges bright
        facing = (gx * self.detector[0] + gy * self.detector[1]) * cos_tilt
        signal = yield_ * (1.0 - 0.3 * facing)  # faces sloping down towards the detector
        signal *= 1.0 + self.rng.normal(0.0, self.noise, signal.shape)
        return SEMImage(pixels=signal, origin=origin, pixel_size=(pitch, pitch))
