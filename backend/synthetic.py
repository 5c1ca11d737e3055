"""Synthetic patch sets as merge inputs, and scoring a merge against their truth.

Ties the simulated world (``hardware.sim``) to the merge engine; the CLI, the benchmarks and
the tests share it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from hardware.sim.synth import SynthPatch, true_points
from merge import Patch, PatchSet, PatchTransform
from merge.kabsch import weighted_rigid_transform

FloatArray = NDArray[np.float64]


def patch_set_from_synth(synth: Sequence[SynthPatch]) -> PatchSet:
    """The merge's view of synthetic patches (without their truth)."""
    return PatchSet(
        Patch(
            id=s.id,
            heights=s.heights,
            origin=s.origin,
            pixel_size=s.pixel_size,
            order=s.order,
            row=s.row,
            col=s.col,
        )
        for s in synth
    )


def registration_error(
    synth: Sequence[SynthPatch], transforms: Sequence[PatchTransform]
) -> tuple[float, float, tuple[FloatArray, FloatArray]]:
    """RMS XY and Z error (metres) of where the merge puts every measured point, after the one
    global rigid transform that fits best (the gauge), and that transform ``(G, g)``."""
    est, true = [], []
    for s, tr in zip(synth, transforms, strict=True):
        ny, nx = s.heights.shape
        xx, yy = np.meshgrid(
            s.origin[0] + np.arange(nx) * s.pixel_size[0],
            s.origin[1] + np.arange(ny) * s.pixel_size[1],
        )
        p = np.stack([xx, yy, s.heights], axis=-1).reshape(-1, 3)
        q = true_points(s).reshape(-1, 3)
        ok = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1)
        est.append(tr.apply(p[ok]))
        true.append(q[ok])
    P, Q = np.concatenate(est), np.concatenate(true)
    G, g = weighted_rigid_transform(P, Q)
    e = P @ G.T + g - Q
    exy = float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1))))
    return exy, float(np.sqrt(np.mean(e[:, 2] ** 2))), (G, g)
