"""The placement of every patch during refinement, in the normal system's units.

Per patch: rotation ``R``, the position of its centre ``s`` and its drift plane, all in units
of the typical pixel (``scale``), so the unknowns of one Gauss-Newton step are of one size.
Converts to and from :class:`merge.core.transforms.PatchTransform` (``T_mosaic_patch``, metres),
applies a step and removes the common motion nothing in the overlaps measures (the gauge).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.transforms import PatchTransform, orthonormalize, rotation_from_vector
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


class MosaicState(PatchState):
    """The placement of every patch (:class:`PatchState`), and how a step and the gauge move it."""

    @classmethod
    def from_transforms(
        cls, start: Sequence[PatchTransform], bank: SurfaceBank, scale: float
    ) -> MosaicState:
        """The state of transforms ``start`` (``T_mosaic_patch``, metres) of ``bank``'s patches,
        lengths in units of ``scale`` (metres)."""
        n = len(start)
        R = np.array([tr.R for tr in start])
        slope = np.array([tr.slope for tr in start])
        s = np.empty((n, 3))
        for c, tr in enumerate(start):
            centre = bank.centre[c] * scale
            # the drift plane is re-centred on the patch centre (a change of its constant only)
            s[c] = (R[c] @ centre + tr.t) / scale
            s[c, 2] += float((centre[:2] - tr.centre) @ tr.slope) / scale
        return cls(R, s, slope)

    def to_transforms(self, bank: SurfaceBank, scale: float) -> list[PatchTransform]:
        """Every patch's ``T_mosaic_patch`` (metres), its drift plane zero at its centre."""
        out = []
        for c in range(len(self.R)):
            centre = bank.centre[c] * scale
            t = self.s[c] * scale - self.R[c] @ centre
            out.append(PatchTransform(self.R[c], t, self.slope[c], centre[:2]))
        return out

    def spin(self) -> FloatArray:
        """Rotation angle about z of every patch, radians."""
        out: FloatArray = np.arctan2(self.R[:, 1, 0], self.R[:, 0, 0])
        return out

    def update(self, delta: FloatArray, radius: FloatArray) -> None:
        """Apply one step ``delta`` (n, 6): translation, then spin and plane times each patch's
        ``radius`` (n,), pixel units."""
        spin = np.zeros((len(delta), 3))
        spin[:, 2] = delta[:, 3] / radius
        self.R = orthonormalize(np.einsum("cij,cjk->cik", rotation_from_vector(spin), self.R))
        self.s = self.s + delta[:, :3]
        self.slope = self.slope + delta[:, 4:] / radius[:, None]

    def fix_gauge(self, centre: FloatArray, points: IntArray) -> None:
        """Remove the common motion (:mod:`merge.refine.icp`'s notes): mean spin, mean plane and
        mean displacement from the nominal ``centre`` (n, 3), weighted by each patch's ``points``
        (n,) (:attr:`merge.refine.bank.SurfaceBank.point_count`)."""
        weight = points.astype(np.float64)
        weight = weight / weight.sum()
        pivot = weight @ self.s
        spin = np.zeros(3)
        spin[2] = -float(weight @ self.spin())
        G = rotation_from_vector(spin)
        self.R = np.einsum("ij,cjk->cik", G, self.R)
        self.s = (self.s - pivot) @ G.T + pivot
        plane = weight @ self.slope
        self.slope = self.slope - plane
        self.s[:, 2] -= (self.s[:, :2] - pivot[:2]) @ plane
        self.s = self.s - weight @ (self.s - centre)
