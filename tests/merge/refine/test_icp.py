"""The refinement: its coarse-to-fine schedule on a real scan, drift-plane prior, stopping."""

from __future__ import annotations

import numpy as np
import pytest

from backend.synthetic import patch_set_from_synth, registration_error
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import Chessboard, FoldedSurface, ImageSurface
from hardware.sim.synth import synthesize
from merge import MergeConfig, pipeline, run
from merge.core.overlap import overlapping_pairs
from merge.core.transforms import PatchTransform
from merge.refine import icp
from merge.refine.convergence import height_effect, remaining
from merge.refine.icp import FAST_DRIFT_SHARE, SIDES, _plane_sigma, heights_prior
from tests.conftest import SHARED_DATA, Synthetic, make_synthetic, narrow_paper_grid, still

GRID = SHARED_DATA / "grid.npy"


@pytest.mark.skipif(not GRID.is_file(), reason=f"the real scans are not at {SHARED_DATA}")
def test_a_real_1d_grating_registers_along_its_stripes() -> None:
    # A 1-D grating fixes XY across its stripes at once; along them only the stripes' slight
    # bends and defects tell, at scales of tens of nm. The coarse start cannot see them, so the
    # refinement begins from the stage error there and needs a basin that wide: with its first
    # level at one pixel of smoothing this draw ended 10 nm off (map error 2.1 x the floor).
    surface = ImageSurface(np.load(GRID), (3e-6 / 256, 3e-6 / 256))
    synth = synthesize(
        surface,
        rows=3,
        cols=3,
        patch_size=(1.172e-6, 1.172e-6),
        pixels=(100, 100),
        overlap=(0.4, 0.4),
        start=(0.3e-6, 0.3e-6),
        drift=DriftModel.typical(),
        seed=1001,
    )
    result = run(patch_set_from_synth(synth))
    by_id = {p.id: p.transform for p in result.patches}
    exy, ez, _ = registration_error(synth, [by_id[s.id] for s in synth])
    assert exy < 7e-9
    assert ez < 1e-9


def test_the_drift_prior_is_the_planes_spread_pooled_with_physics_unless_wider() -> None:
    rng = np.random.default_rng(0)
    physics = np.array([5.0 * FAST_DRIFT_SHARE, 5.0])
    spread = np.array([0.2, 3.0])  # a drift in time: tilts across the lines
    # a mosaic's planes say how large the drift is; a few patches say little. The drift's
    # prior enters once per side of the data, as they do: its sigma per side is the drift's
    # times sqrt(SIDES)
    per_side = np.sqrt(SIDES)
    many = _plane_sigma(rng.normal(0.0, spread, (10_000, 2)), 5.0) * per_side
    np.testing.assert_allclose(many, spread, rtol=0.02)
    few = _plane_sigma(rng.normal(0.0, spread, (2, 2)), 5.0) * per_side
    assert np.all(few < physics) and np.all(few > 0.85 * physics)
    some = _plane_sigma(rng.normal(0.0, spread, (50, 2)), 5.0) * per_side
    assert np.all(some > many) and np.all(some < few)
    # the physical bound holds however wide the drift planes spread below the drift itself
    wide = _plane_sigma(rng.normal(0.0, [2.0, 4.0], (10_000, 2)), 5.0) * per_side
    assert wide[0] == pytest.approx(physics[0]) and wide[1] == pytest.approx(4.0, rel=0.02)
    # tilts along the lines too, wider than a drift: not a drift, and the prior a mere limit
    levelled = _plane_sigma(rng.normal(0.0, [40.0, 3.0], (50, 2)), 5.0)
    assert levelled[0] == pytest.approx(40.0, rel=0.25) and levelled[1] < 5.0


def test_a_step_moves_heights_directly_in_z_and_through_the_slopes_in_xy() -> None:
    delta = np.zeros((2, 6))
    delta[0, :2] = [0.3, 0.4]  # 0.5 px of XY on slopes of RMS 0.2: 0.1 px of height
    delta[1, 2] = 0.05  # Z
    delta[1, 4:] = [0.03, 0.04]  # the drift plane, at the patch radius
    assert height_effect(delta, 0.2) == pytest.approx(0.1)
    assert height_effect(delta, 0.0) == pytest.approx(0.1)  # 0.05 + 0.05 of patch 1
    assert height_effect(delta, np.inf) == np.inf  # not the raw level: never by this rule


def test_what_remains_of_a_geometric_convergence_is_its_tail() -> None:
    # steps shrinking by 5 each: 1, 0.2, 0.04, ... leave 0.05 after the second
    assert remaining(0.2, 1.0) == pytest.approx(0.05)
    # slow convergence (ratio over a half) or a first step: the last step alone
    assert remaining(0.8, 1.0) == 0.8
    assert remaining(0.2, np.inf) == 0.2
    assert remaining(1.5, 1.0) == 1.5  # growing: no tail to sum
    assert remaining(np.inf, np.inf) == np.inf  # coarse levels: never by this rule
    # a ratio known to be at least 0.5 (the last level's): a jump 1 -> 0.2 proves nothing faster
    assert remaining(0.2, 1.0, at_least=0.5) == 0.2
    assert remaining(0.2, 1.0, at_least=0.1) == pytest.approx(0.05)  # the step's own ratio


def test_patches_still_moving_when_the_iterations_run_out_are_named(
    small_mosaic: Synthetic,
) -> None:
    patches = small_mosaic.patch_set.patches
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=1e-7)
    start = [PatchTransform() for _ in patches]  # nominal: every patch off by its stage error
    one_step = icp.Level(0.0, 1, 1, 1e-3)
    stopped = icp.refine(patches, pairs, start, levels=(one_step,))
    assert not stopped.converged
    assert stopped.unsettled is not None and stopped.unsettled.any()
    settled = icp.refine(patches, pairs, start)
    assert settled.converged and settled.unsettled is None
    # the report takes them for what they are
    capped = pipeline.run(small_mosaic.patch_set, MergeConfig(max_iter=1))
    assert not capped.converged
    flagged = [r.id for r in capped.patches if not r.xy_constrained]
    assert flagged and all(any(f"{i!r}" in w for w in capped.warnings) for i in flagged)


def test_the_first_level_moves_only_the_free_patches(small_mosaic: Synthetic) -> None:
    patches = small_mosaic.patch_set.patches
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=1e-7)
    start = [PatchTransform() for _ in patches]  # nominal: every patch is off by its stage error
    free = np.zeros(len(patches), dtype=bool)
    free[2] = True
    fit = icp.refine(patches, pairs, start, levels=icp.DEFAULT_LEVELS[:1], first_free=free)
    moved = [float(np.abs(tr.t - s.t).max()) for tr, s in zip(fit.transforms, start, strict=True)]
    assert moved[2] > 5e-9
    assert max(m for m, f in zip(moved, free, strict=True) if not f) < 1e-12


@pytest.mark.parametrize(
    ("step", "pixels", "smoothed"),
    [
        # a grating's flat squares in 5 nm pixels: the look-ups' slopes are mostly noise
        (0.6e-6, (200, 200), True),
        # a flat face's roughness at the pixel's scale in 20 nm pixels: it is all signal
        (0.0, (50, 50), False),
    ],
)
def test_the_raw_level_smooths_the_slopes_only_where_the_pixels_are_finer_than_the_texture(
    step: float, pixels: tuple[int, int], smoothed: bool
) -> None:
    synth = synthesize(
        Chessboard(period=3e-6, step=step, edge_width=50e-9, seed=4),
        rows=2,
        cols=2,
        patch_size=(1e-6, 1e-6),
        pixels=pixels,
        overlap=(0.25, 0.25),
        drift=DriftModel.typical(),
        seed=3,
    )
    patches = patch_set_from_synth(synth).patches
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=1e-7)
    fit = icp.refine(patches, pairs, [PatchTransform() for _ in patches])
    slopes = fit.bank.source_slopes
    assert (slopes is not None) is smoothed
    if slopes is not None:
        assert slopes.width > 0 and len(slopes.grids) == len(patches)


def test_a_mosaic_of_narrow_overlaps_settles_instead_of_cycling() -> None:
    # 15 % overlaps of 30 x 60 px patches: strips 4 px wide gain and lose a border column in
    # turn, and the raw level went back and forth between two placements until its iterations
    # ran out (34), every patch then reported as not settled
    synth = narrow_paper_grid(FoldedSurface(seed=101001), 101001)
    result = run(patch_set_from_synth(synth))
    assert result.converged
    assert not [w for w in result.warnings if "ran out of iterations" in w]
    exy, _, _ = registration_error(synth, [p.transform for p in result.patches])
    assert exy < 1e-9


def test_the_heights_solve_takes_one_lines_share_of_the_drift_along_the_lines() -> None:
    # counted once, the level's sigmas per side of the data grow by sqrt(SIDES); along the
    # lines a drift in time moves by one line's share of what it moves across them
    drift = 5.0
    held = heights_prior(np.array([0.3, 2.0]), drift, 200.0)
    assert held[1] == pytest.approx(2.0 * np.sqrt(SIDES))
    assert held[0] == pytest.approx(2.0 * np.sqrt(SIDES) / 200.0)
    # never looser along the lines than the level's own
    assert heights_prior(np.array([0.001, 2.0]), drift, 200.0)[0] == pytest.approx(
        0.001 * np.sqrt(SIDES)
    )
    # patches levelled one by one: the spread the level followed stays, along either axis
    levelled = heights_prior(np.array([40.0, 30.0]), drift, 200.0)
    np.testing.assert_allclose(levelled, [40.0, 30.0])


def test_a_wide_mosaics_smoothed_level_leaves_out_the_borders_its_continuation_bends(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # two noise-free folded patches at their true places: the one-pixel level's point-symmetric
    # continuation bends both near their borders, and moves the pair; its border band does not
    pair = make_synthetic(
        FoldedSurface(seed=2),
        rows=1,
        cols=2,
        seed=2,
        drift=still(0.0),
        patch_size=(1e-6, 1e-6),
        pixels=(64, 64),
        overlap=(0.25, 0.25),
    )
    patches = pair.patch_set.patches
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=1e-7)
    start = [PatchTransform() for _ in patches]
    one_pixel = (icp.DEFAULT_LEVELS[1],)
    assert one_pixel[0].smooth > 0 and one_pixel[0].band == 0

    def moved() -> float:
        fit = icp.refine(patches, pairs, start, levels=one_pixel)
        return float(np.abs(fit.transforms[1].t[:2] - fit.transforms[0].t[:2]).max())

    assert moved() > 0.5e-9  # two patches span 1.75: no band
    monkeypatch.setattr(icp, "WIDE_SPAN", 1.5)
    assert moved() < 0.1e-9
