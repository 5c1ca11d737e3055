"""Shared fixtures: small synthetic patch sets with known truth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from hardware.sim.synth import SynthPatch, synthesize, true_points
from merge import Patch, PatchSet, PatchTransform
from merge.kabsch import weighted_rigid_transform


@dataclass
class Synthetic:
    synth: list[SynthPatch]
    patch_set: PatchSet
    surface: FoldedSurface

    def registration_error(self, transforms: list[PatchTransform]) -> tuple[float, float]:
        """RMS XY and Z error (m) over all points after the best global rigid transform."""
        est, true = [], []
        for s, tr in zip(self.synth, transforms, strict=True):
            ny, nx = s.heights.shape
            xx, yy = np.meshgrid(
                s.origin[0] + np.arange(nx) * s.pixel_size[0],
                s.origin[1] + np.arange(ny) * s.pixel_size[1],
            )
            p = np.stack([xx, yy, s.heights], -1).reshape(-1, 3)
            est.append(tr.apply(p))
            true.append(true_points(s).reshape(-1, 3))
        P, Q = np.concatenate(est), np.concatenate(true)
        G, g = weighted_rigid_transform(P, Q)
        e = P @ G.T + g - Q
        return float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))), float(
            np.sqrt(np.mean(e[:, 2] ** 2))
        )


@pytest.fixture(scope="session")
def folded() -> FoldedSurface:
    return FoldedSurface(seed=7)


def make_synthetic(
    surface: FoldedSurface,
    *,
    rows: int = 2,
    cols: int = 3,
    seed: int = 1,
    drift: DriftModel | None = None,
) -> Synthetic:
    synth = synthesize(
        surface,
        rows=rows,
        cols=cols,
        patch_size=(0.8e-6, 0.8e-6),
        pixels=(40, 40),
        overlap=(0.4, 0.4),
        drift=drift or DriftModel.typical(),
        seed=seed,
    )
    ps = PatchSet(
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
    return Synthetic(synth, ps, surface)


@pytest.fixture(scope="session")
def small_mosaic(folded: FoldedSurface) -> Synthetic:
    """2 x 3 patches of 40 x 40 pixels on the folded surface with typical drift."""
    return make_synthetic(folded)
