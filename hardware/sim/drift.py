"""Errors of a mosaic acquisition: stage positioning, rotation, Z drift and noise per patch.

The model follows the acquisition order. The coarse stage lands every patch with an independent
XY error and a small rotation of the scan frame; the Z reference drifts as a staircase (charging
and creep add up from one patch to the next); inside a patch Z drifts linearly in scan time; every
pixel carries white noise and every scan line an offset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DriftModel:
    """Statistics of the errors (SI units).

    stage_sigma : XY positioning error of the coarse stage per axis, metres.
    rotation_sigma_deg : rotation of each patch's scan frame, degrees.
    z_step_mean, z_step_sigma : step of the Z staircase from one patch to the next, metres.
    z_drift_sigma : linear Z drift inside a patch, over the whole patch, metres.
    noise : white height noise per pixel, metres.
    line_noise : offset per scan line, metres.
    """

    stage_sigma: float = 50e-9
    rotation_sigma_deg: float = 0.3
    z_step_mean: float = 25e-9
    z_step_sigma: float = 20e-9
    z_drift_sigma: float = 4e-9
    noise: float = 1e-9
    line_noise: float = 0.3e-9

    @classmethod
    def typical(cls) -> DriftModel:
        """Mid-range values of the merge issue's drift model."""
        return cls()

    @classmethod
    def harsh(cls) -> DriftModel:
        """The harsh end of every range."""
        return cls(
            stage_sigma=80e-9,
            rotation_sigma_deg=0.5,
            z_step_mean=40e-9,
            z_step_sigma=30e-9,
        )

    def scaled(self, factor: float) -> DriftModel:
        """The same model with the XY and Z-staircase errors scaled (for other patch sizes)."""
        return DriftModel(
            stage_sigma=self.stage_sigma * factor,
            rotation_sigma_deg=self.rotation_sigma_deg,
            z_step_mean=self.z_step_mean * factor,
            z_step_sigma=self.z_step_sigma * factor,
            z_drift_sigma=self.z_drift_sigma,
            noise=self.noise,
            line_noise=self.line_noise,
        )

    def draw(self, n: int, rng: np.random.Generator) -> PatchErrors:
        """Errors of ``n`` patches in acquisition order."""
        steps = rng.normal(self.z_step_mean, self.z_step_sigma, n)
        steps[0] = 0.0
        return PatchErrors(
            stage_xy=rng.normal(0.0, self.stage_sigma, (n, 2)),
            rotation=np.radians(rng.normal(0.0, self.rotation_sigma_deg, n)),
            z_offset=np.cumsum(steps),
            z_drift=rng.normal(0.0, self.z_drift_sigma, n),
        )


@dataclass(frozen=True)
class PatchErrors:
    """Drawn errors, one row per patch in acquisition order.

    stage_xy : (n, 2) metres; rotation : (n,) radians about the patch centre;
    z_offset : (n,) metres added to every height; z_drift : (n,) metres of linear drift from
    the first to the last pixel (centred on the middle of the scan).
    """

    stage_xy: FloatArray
    rotation: FloatArray
    z_offset: FloatArray
    z_drift: FloatArray
