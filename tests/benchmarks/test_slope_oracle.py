"""The slope oracle (benchmarks/slope_oracle.py): its true slopes are the merge's own, in its
frames, and the build gets its own rows back."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from backend.synthetic import patch_set_from_synth
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from hardware.sim.synth import SynthPatch, synthesize
from merge.core.transforms import PatchTransform
from merge.refine import normal_system
from merge.refine.bank import SurfaceBank
from merge.refine.rows import residuals
from merge.refine.state import MosaicState

# the benchmarks are scripts beside each other, not a package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from slope_oracle import oracle_slopes, true_slopes

#: A surface smooth at the pixel scale of 5 nm pixels.
SURFACE = FoldedSurface(seed=3)


def _two_patches(pixels: int, overlap: float, drift: DriftModel) -> list[SynthPatch]:
    """Two 1 µm patches side by side of :data:`SURFACE`, ``pixels`` a side."""
    return synthesize(
        SURFACE,
        rows=1,
        cols=2,
        patch_size=(1e-6, 1e-6),
        pixels=(pixels, pixels),
        overlap=(overlap, overlap),
        drift=drift,
        seed=5,
    )


def test_true_slopes_are_what_the_look_ups_see_of_a_smooth_noise_free_surface() -> None:
    # two turned patches of a surface smooth at the pixel scale (5 nm pixels), no noise and no
    # drift: the look-ups' slopes (a pixel either side on the spline) are the surface's own,
    # so the oracle's, taken from the truth in world coordinates, must agree with them row by
    # row (6 % apart: the folds' finest detail); a frame wrong by the patches' turn would not
    drift = DriftModel(rotation_sigma_deg=20.0, z_drift_sigma=0.0, noise=0.0, line_noise=0.0)
    synth = _two_patches(200, 0.5, drift)
    spins = [np.degrees(np.arctan2(s.rotation[1, 0], s.rotation[0, 0])) for s in synth]
    assert min(abs(a) for a in spins) > 10.0  # the draw turns both patches well
    patches = patch_set_from_synth(synth).patches
    scale = synth[0].pixel_size[0]
    bank = SurfaceBank(patches, scale, 0.0, 1)
    truth = [PatchTransform(s.rotation, s.translation) for s in synth]
    state = MosaicState.from_transforms(truth, bank, scale)
    runs = bank.candidates(np.array([[0, 1]]), state.R, state.s, 0.0)
    rows = bank.rows(runs)
    _, ok, seen, _ = residuals(bank, rows, state)
    exact = true_slopes(bank, rows, state, synth, SURFACE)
    assert ok.sum() > 500
    d = exact[ok] - seen[ok]
    assert np.sqrt(np.mean(d**2)) < 0.1 * np.sqrt(np.mean(exact[ok] ** 2))


def test_the_oracle_gives_the_build_its_own_rows_back_when_it_ends() -> None:
    own = vars(normal_system)["residuals"]
    synth = _two_patches(20, 0.3, DriftModel.typical())
    with oracle_slopes(synth, SURFACE):
        assert vars(normal_system)["residuals"] is not own
    assert vars(normal_system)["residuals"] is own
