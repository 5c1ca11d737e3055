"""Patch reports from the assessment's fits: what counts as XY held, and what is said of it."""

from __future__ import annotations

import numpy as np

from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform
from merge.report import PatchFit, patch_reports


def _patch(name: str, x0: float) -> Patch:
    rng = np.random.default_rng(len(name))
    return Patch(
        id=name, heights=rng.normal(0, 1e-9, (8, 8)), origin=(x0, 0.0), pixel_size=(1e-8, 1e-8)
    )


def test_a_patch_whose_own_overlaps_do_not_hold_xy_is_flagged_and_warned_of() -> None:
    patches = [_patch("held", 0.0), _patch("loose", 6e-8), _patch("alone", 1e-6)]
    fits = [
        PatchFit(
            correspondences=40,
            residual_rms=1e-9,
            xy_sigma=1e-10,
            z_sigma=1e-10,
            xy_sigma_local=1e-10,
        ),
        PatchFit(
            correspondences=40, residual_rms=1e-9, xy_sigma=5e-9, z_sigma=1e-10, xy_sigma_local=5e-9
        ),
        PatchFit(
            correspondences=0,
            residual_rms=np.nan,
            xy_sigma=np.inf,
            z_sigma=np.inf,
            xy_sigma_local=np.inf,
        ),
    ]
    shifted = PatchTransform(t=np.array([1e-9, -2e-9, 3e-9]))
    transforms = [shifted, PatchTransform(), PatchTransform()]
    linked = np.array([True, True, False])
    reports, warnings = patch_reports(patches, transforms, fits, linked, registered=True)
    assert [r.xy_constrained for r in reports] == [True, False, False]
    assert [r.overlaps for r in reports] == [True, True, False]
    np.testing.assert_array_equal(reports[0].translation, shifted.t)  # rigid: its own t
    # only a patch with overlaps is warned of; one that overlaps nothing is the layout's business
    assert len(warnings) == 1 and "'loose'" in warnings[0]
    _, quiet = patch_reports(patches, transforms, fits, linked, registered=False)
    assert quiet == []  # z-levelling never claimed XY


def test_a_patch_the_refinement_left_moving_is_not_called_held() -> None:
    # however sharp its fit looks, a patch still moving when the refinement ran out of
    # iterations sits where the fit stopped
    patches = [_patch("settled", 0.0), _patch("moving", 6e-8)]
    sharp = PatchFit(
        correspondences=40, residual_rms=1e-9, xy_sigma=1e-10, z_sigma=1e-10, xy_sigma_local=1e-10
    )
    transforms = [PatchTransform(), PatchTransform()]
    linked = np.array([True, True])
    reports, warnings = patch_reports(
        patches,
        transforms,
        [sharp, sharp],
        linked,
        registered=True,
        unsettled=np.array([0, 1], bool),
    )
    assert [r.xy_constrained for r in reports] == [True, False]
    assert (
        len(warnings) == 1 and "'moving'" in warnings[0] and "ran out of iterations" in warnings[0]
    )


def test_a_patch_its_texture_does_not_confirm_is_not_called_held() -> None:
    # placed by the refinement alone on texture weaker than the noise: a dip of the noise
    patches = [_patch("confirmed", 0.0), _patch("doubted", 6e-8), _patch("apart", 1.2e-7)]
    sharp = PatchFit(
        correspondences=40, residual_rms=1e-9, xy_sigma=1e-10, z_sigma=1e-10, xy_sigma_local=1e-10
    )
    reports, warnings = patch_reports(
        patches,
        [PatchTransform()] * 3,
        [sharp] * 3,
        np.array([True, True, True]),
        registered=True,
        unconfirmed={1: 0.4, 2: float("nan")},
    )
    assert [r.xy_constrained for r in reports] == [True, False, False]
    assert len(warnings) == 2
    assert "'doubted'" in warnings[0] and "rises by only 0.4 standard errors" in warnings[0]
    assert "'apart'" in warnings[1] and "no move off it" in warnings[1]


def test_a_patch_its_overlaps_do_not_fit_is_not_called_held() -> None:
    # a residual twenty times what the noise explains: the patch lies on a wrong match, however
    # sharp the fit; on noise-free heights there is nothing to judge a misfit by
    patches = [_patch("fits", 0.0), _patch("astray", 6e-8)]
    flat = Patch(id="flat", heights=np.zeros((8, 8)), origin=(1.2e-7, 0.0), pixel_size=(1e-8, 1e-8))
    noise = patches[1].noise
    misfit = 20.0 * np.sqrt(2.0) * noise

    def sharp(residual: float) -> PatchFit:
        return PatchFit(
            correspondences=40,
            residual_rms=residual,
            xy_sigma=1e-10,
            z_sigma=1e-10,
            xy_sigma_local=1e-10,
        )

    fits = [sharp(noise), sharp(misfit), sharp(misfit)]
    reports, warnings = patch_reports(
        [*patches, flat],
        [PatchTransform()] * 3,
        fits,
        np.array([True, True, True]),
        registered=True,
    )
    assert [r.xy_constrained for r in reports] == [True, False, True]
    assert len(warnings) == 1 and "'astray'" in warnings[0] and "do not fit" in warnings[0]
    assert "20 x" in warnings[0]
