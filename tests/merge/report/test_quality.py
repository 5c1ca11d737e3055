"""The per-patch quality report: residuals, and how well each patch is placed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hardware.sim.surfaces import FoldedSurface
from merge import Patch, PatchSet, PatchTransform, run
from merge.core.overlap import overlapping_pairs
from merge.refine import DEFAULT_LEVELS, refine
from merge.report.quality import PatchFit, assess
from tests.conftest import Synthetic, make_synthetic, still

NOISE = 1e-9
#: No drift at all: the nominal placement is the truth.
STILL = still(NOISE)


@pytest.fixture(scope="module")
def still(folded: FoldedSurface) -> Synthetic:
    return make_synthetic(folded, drift=STILL)


def _assess(patch_set: PatchSet, transforms: list[PatchTransform]) -> list[PatchFit]:
    patches = list(patch_set)
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]))
    return assess(patches, pairs, transforms)


def test_at_the_truth_residuals_are_the_noise_and_every_patch_is_placed(still: Synthetic) -> None:
    fits = _assess(still.patch_set, [PatchTransform() for _ in still.synth])
    for f in fits:
        assert f.correspondences > 100
        # the height of a point above the other's bilinear surface: both noises, the
        # surface's a little averaged
        assert NOISE < f.residual_rms < 1.6 * NOISE
        assert f.xy_sigma < 2e-9 and f.z_sigma < 0.5 * NOISE
        assert f.xy_sigma_local <= f.xy_sigma * 1.001  # others held: never worse


def test_a_misplaced_patch_shows_in_its_residuals(still: Synthetic) -> None:
    transforms = [PatchTransform() for _ in still.synth]
    transforms[2] = PatchTransform(t=np.array([6e-8, 0.0, 0.0]))  # three pixels in x
    fits = _assess(still.patch_set, transforms)
    others = np.median([f.residual_rms for k, f in enumerate(fits) if k != 2])
    assert fits[2].residual_rms > 2.0 * others


def test_flat_overlaps_leave_xy_unseen_and_a_lone_patch_unmeasured() -> None:
    rng = np.random.default_rng(0)
    # white noise only, the patches a fraction of a pixel apart (as stage errors put them)
    corners = [(0.0, 0.0), (3.07e-7, 0.83e-8), (6.11e-7, 0.3e-8), (5e-6, 0.0)]
    patches = [
        Patch(
            id=f"f{k}",
            heights=rng.normal(0.0, NOISE, (30, 30)),
            origin=corner,
            pixel_size=(2e-8, 2e-8),
        )
        for k, corner in enumerate(corners)
    ]
    fits = _assess(PatchSet(patches), [PatchTransform() for _ in patches])
    for f in fits[:3]:
        assert f.correspondences > 0
        assert f.xy_sigma_local == f.xy_sigma == np.inf  # white noise is no texture
        assert f.z_sigma < 0.1 * NOISE  # hundreds of points on each overlap
    # the last overlaps nothing: nothing measured, and it takes nothing from the others
    lone = fits[3]
    assert lone.correspondences == 0 and np.isnan(lone.residual_rms)
    assert lone.xy_sigma == lone.z_sigma == np.inf
    # (but for the noise estimate, a median over the patches that now counts one more)
    alone = _assess(PatchSet(patches[:3]), [PatchTransform() for _ in patches[:3]])
    assert [f.z_sigma for f in fits[:3]] == pytest.approx([f.z_sigma for f in alone], rel=0.05)


def test_the_refinements_settled_system_reports_as_a_build_at_its_result(
    small_mosaic: Synthetic,
) -> None:
    """The report takes the system of the refinement's last step when that step settled the
    fit: the transforms it reports on are one such step further, and a system built there
    reports the same within a few per cent (the residuals it holds still have that step's
    misfit in them)."""
    patches = list(small_mosaic.patch_set)
    boxes = np.array([p.footprint for p in patches])
    pairs = overlapping_pairs(boxes, margin=1e-7)
    start = [PatchTransform() for _ in patches]
    fit = refine(patches, pairs, start, report=True)
    assert fit.converged and fit.system is not None and fit.system.signal_vals is not None
    kept = assess(patches, pairs, fit.transforms, bank=fit.bank, system=fit.system)
    fresh = assess(patches, pairs, fit.transforms, bank=fit.bank)
    for k, f in zip(kept, fresh, strict=True):
        assert abs(k.correspondences - f.correspondences) <= 0.002 * f.correspondences
        assert k.residual_rms == pytest.approx(f.residual_rms, rel=0.01)
        assert k.xy_sigma == pytest.approx(f.xy_sigma, rel=0.03)
        assert k.z_sigma == pytest.approx(f.z_sigma, rel=0.05)
    # not asked for, or out of iterations before the fit settled: none kept
    assert refine(patches, pairs, start).system is None
    short = tuple(replace(lv, max_iter=1) for lv in DEFAULT_LEVELS)
    assert refine(patches, pairs, start, levels=short, report=True).system is None


def test_the_report_counts_the_drift_prior_the_refinement_solved_with(
    small_mosaic: Synthetic,
) -> None:
    """The drift planes' prior holds what overlaps measure weakly (the patches' relative tilts
    across their scan lines, and with them Z): counted as the refinement's steps counted it, it
    only adds information, so no sigma grows and Z's shrink; a merge reports with it."""
    patches = list(small_mosaic.patch_set)
    boxes = np.array([p.footprint for p in patches])
    pairs = overlapping_pairs(boxes, margin=1e-7)
    fit = refine(patches, pairs, [PatchTransform() for _ in patches], report=True)
    assert fit.plane_sigma is not None and np.isfinite(fit.plane_sigma).all()

    def with_prior(plane_sigma: np.ndarray | None) -> list[PatchFit]:
        return assess(
            patches,
            pairs,
            fit.transforms,
            bank=fit.bank,
            system=fit.system,
            plane_sigma=plane_sigma,
        )

    data, held = with_prior(None), with_prior(fit.plane_sigma)
    z_data = np.array([f.z_sigma for f in data])
    z_held = np.array([f.z_sigma for f in held])
    assert (z_held <= z_data * (1 + 1e-9)).all()
    assert np.median(z_held / z_data) < 0.95
    for d, h in zip(data, held, strict=True):
        assert h.xy_sigma <= d.xy_sigma * (1 + 1e-9)
        assert h.residual_rms == d.residual_rms
    # a loose prior is the data alone
    loose = with_prior(np.full(2, 1e12))
    np.testing.assert_allclose([f.z_sigma for f in loose], z_data, rtol=1e-6)
    # the pipeline hands the prior on: a merge's Z sigmas are those held by it
    merged = run(small_mosaic.patch_set)
    by_id = {r.id: r for r in merged.patches}
    reported = np.array([by_id[p.id].z_sigma for p in patches])
    alone = assess(patches, pairs, [by_id[p.id].transform for p in patches])
    assert np.median(reported / np.array([f.z_sigma for f in alone])) < 0.95
