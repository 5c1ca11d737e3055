"""Shared fixtures: small synthetic patch sets with known truth."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from backend.synthetic import patch_set_from_synth, registration_error
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface, ImageSurface, Surface, TipDrawnChessboard
from hardware.sim.synth import SynthPatch, synthesize
from merge import PatchSet, PatchTransform


def _shared_data() -> Path:
    """The real scans of ``../shared/data`` (MOSAIC_SHARED_DATA overrides where it is)."""
    given = os.environ.get("MOSAIC_SHARED_DATA")
    return Path(given) if given else Path(__file__).resolve().parents[2] / "shared" / "data"


#: Where the real AFM scans are; tests that need them skip when they are missing.
SHARED_DATA = _shared_data()


@dataclass
class Synthetic:
    synth: list[SynthPatch]
    patch_set: PatchSet
    surface: Surface

    def registration_error(self, transforms: list[PatchTransform]) -> tuple[float, float]:
        """RMS XY and Z error (m) over all points after the gauge that fits best."""
        exy, ez, _ = registration_error(self.synth, transforms)
        return exy, ez


@pytest.fixture(scope="session")
def folded() -> FoldedSurface:
    return FoldedSurface(seed=7)


def make_synthetic(
    surface: Surface,
    *,
    rows: int = 2,
    cols: int = 3,
    seed: int = 1,
    drift: DriftModel | None = None,
    patch_size: tuple[float, float] = (0.8e-6, 0.8e-6),
    pixels: tuple[int, int] = (40, 40),
    overlap: tuple[float, float] = (0.4, 0.4),
    bend: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> Synthetic:
    synth = synthesize(
        surface,
        rows=rows,
        cols=cols,
        patch_size=patch_size,
        pixels=pixels,
        overlap=overlap,
        drift=drift or DriftModel.typical(),
        seed=seed,
        bend=bend,
    )
    ps = patch_set_from_synth(synth)
    return Synthetic(synth, ps, surface)


@pytest.fixture(scope="session")
def small_mosaic(folded: FoldedSurface) -> Synthetic:
    """2 x 3 patches of 40 x 40 pixels on the folded surface with typical drift."""
    return make_synthetic(folded)


def stripes_mosaic() -> Synthetic:
    """2 x 2 patches of 60 x 60 px on a 1-D grating at 45 degrees, stripes 300 nm apart
    across, with a faint roughness: a sample whose overlaps repeat themselves."""
    yy, xx = np.mgrid[0:300, 0:300] * 10e-9
    heights = 15e-9 * np.sin(2 * np.pi * (xx + yy) / np.sqrt(2) / 300e-9)
    rough = np.random.default_rng(3).normal(0.0, 0.3e-9, heights.shape)
    grating = ImageSurface(heights + rough, (10e-9, 10e-9))
    return make_synthetic(grating, rows=2, cols=2, pixels=(60, 60), overlap=(0.45, 0.45))


def still(noise: float) -> DriftModel:
    """No drift at all but white ``noise`` (metres): the nominal placement is the truth."""
    return DriftModel(
        stage_sigma=0.0,
        rotation_sigma_deg=0.0,
        z_step_mean=0.0,
        z_step_sigma=0.0,
        z_drift_sigma=0.0,
        noise=noise,
        line_noise=0.0,
    )


def paper_grid(
    surface: Surface,
    seed: int,
    *,
    overlap: tuple[float, float] = (0.5, 1 / 3),
    drift: DriftModel | None = None,
) -> list[SynthPatch]:
    """The paper's grid: 5 x 10 patches of 0.6 x 1.2 um in 30 x 60 px, overlaps of a half and a
    third unless ``overlap`` says, under ``drift`` (default the typical)."""
    return synthesize(
        surface,
        rows=5,
        cols=10,
        patch_size=(0.6e-6, 1.2e-6),
        pixels=(30, 60),
        overlap=overlap,
        drift=drift or DriftModel.typical(),
        seed=seed,
    )


def narrow_paper_grid(surface: Surface, seed: int) -> list[SynthPatch]:
    """The paper's grid with overlaps of only 15 % both ways, under the typical drift: strips a
    few pixels wide, two stage errors."""
    return paper_grid(surface, seed, overlap=(0.15, 0.15))


def tip_drawn_paper_grid(drift: DriftModel | None = None) -> Synthetic:
    """The paper's grid of its own sample as a tip draws it (:class:`TipDrawnChessboard`: 0.6 um
    steps, straight flanks meeting the faces in kinks), under ``drift`` (default the typical)."""
    surface = TipDrawnChessboard(seed=11)
    synth = paper_grid(surface, 11, drift=drift)
    return Synthetic(synth, patch_set_from_synth(synth), surface)
