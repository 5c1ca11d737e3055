"""Scoring a merge against the truth of a synthetic patch set (``backend.synthetic``)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.synthetic import patch_errors, registration_error, scored
from merge import PatchTransform
from tests.conftest import Synthetic


def _shifted(small_mosaic: Synthetic, shift: float) -> list[PatchTransform]:
    """Every other patch moved by ``shift`` metres along x from its true place."""
    out = []
    for k, s in enumerate(small_mosaic.synth):
        t = np.array(s.translation, dtype=float)
        t[0] += shift * (k % 2)
        out.append(PatchTransform(s.rotation, t))
    return out


def test_the_true_transforms_err_by_the_drift_alone(small_mosaic: Synthetic) -> None:
    truth = [PatchTransform(s.rotation, s.translation) for s in small_mosaic.synth]
    exy, ez, _ = registration_error(small_mosaic.synth, truth)
    # the Z drift during each scan is left, and tilts the gauge's fit a little
    assert exy < 0.5e-9
    assert 0 < ez < 2e-9


def test_a_stride_samples_the_same_error(small_mosaic: Synthetic) -> None:
    moved = _shifted(small_mosaic, 4e-9)
    full = registration_error(small_mosaic.synth, moved)
    thin = registration_error(small_mosaic.synth, moved, stride=4)
    # half the patches 4 nm off: 2 nm RMS about the gauge, whatever points are counted
    assert full[0] == pytest.approx(2e-9, rel=0.05)
    assert thin[0] == pytest.approx(full[0], rel=0.05)


def test_a_stride_must_be_positive(small_mosaic: Synthetic) -> None:
    with pytest.raises(ValueError, match="stride must be a positive integer"):
        registration_error(small_mosaic.synth, [PatchTransform()] * 6, stride=0)


def _exact(small_mosaic: Synthetic, plane: tuple[float, float]) -> list[PatchTransform]:
    """The true transforms, each scan's Z drift taken out as its drift plane, with one plane
    ``z += a x + b y`` added to the whole mosaic."""
    out = []
    for s in small_mosaic.synth:
        (ny, nx), (dx, dy) = s.heights.shape, s.pixel_size
        # the drift is z_drift (s - 1/2) at scan fraction s = (row nx + col) / (nx ny)
        drift = np.array([-s.z_drift / (nx * ny * dx), -s.z_drift / (ny * dy)])
        # the plane at the mosaic's place of every point: (a, b) . (R_xy p_xy + t_xy)
        turn, ab, origin = s.rotation[:2, :2], np.array(plane), np.array(s.origin)
        t = np.array(s.translation, dtype=float)
        t[2] += 0.5 * s.z_drift + ab @ (turn @ origin + t[:2])
        out.append(PatchTransform(s.rotation, t, drift + turn.T @ ab, origin))
    return out


def test_a_plane_common_to_all_patches_is_the_gauge_not_an_error(small_mosaic: Synthetic) -> None:
    # drift planes are measured only against each other: a mosaic is levelled up to one plane,
    # which a tilt of the gauge would turn into XY errors as large as the tilt times the heights
    level = registration_error(small_mosaic.synth, _exact(small_mosaic, (0.0, 0.0)))
    tilted = registration_error(small_mosaic.synth, _exact(small_mosaic, (1.5e-3, -2e-3)))
    assert level[0] < 1e-12 and level[1] < 1e-12
    assert tilted[0] < 2e-12 and tilted[1] < 2e-12
    np.testing.assert_allclose(tilted[2][0][2, :2], (-1.5e-3, 2e-3), rtol=0.02)


def test_patch_errors_sample_with_a_stride(small_mosaic: Synthetic) -> None:
    moved = _shifted(small_mosaic, 4e-9)
    full = patch_errors(small_mosaic.synth, moved)
    thin = patch_errors(small_mosaic.synth, moved, stride=4)
    # every other patch 4 nm off along x: about +-2 nm from the gauge (its rotation takes a
    # little), whatever points are counted
    np.testing.assert_allclose(np.abs(full[:, 0]), 2e-9, rtol=0.1)
    np.testing.assert_allclose(thin[:, :2], full[:, :2], atol=0.1e-9)
    # in Z, every 4th line of a patch is scanned a little earlier on average: its drift differs
    np.testing.assert_allclose(thin[:, 2], full[:, 2], atol=0.25e-9)
    with pytest.raises(ValueError, match="stride must be a positive integer"):
        patch_errors(small_mosaic.synth, moved, stride=0)


def test_patches_judged_among_themselves_are_not_pulled_by_one_far_off(
    small_mosaic: Synthetic,
) -> None:
    truth = [PatchTransform(s.rotation, s.translation) for s in small_mosaic.synth]
    far = list(truth)
    t = np.array(truth[0].t, dtype=float)
    t[0] += 200e-9  # one patch lost: a merge would report it loose
    far[0] = PatchTransform(truth[0].R, t)
    held = np.ones(len(far), dtype=bool)
    held[0] = False
    pulled = np.hypot(*scored(small_mosaic.synth, far).patches[1:, :2].T)
    among = np.hypot(*scored(small_mosaic.synth, far, gauge_on=held).patches[:, :2].T)
    # fitted to all, the gauge follows the lost patch by its share, and the rest look off
    assert pulled.min() > 200e-9 / len(far) / 2
    assert among[1:].max() < 0.5e-9 and among[0] == pytest.approx(200e-9, rel=0.01)
    with pytest.raises(ValueError, match="must mark some"):
        scored(small_mosaic.synth, far, gauge_on=np.zeros(len(far), dtype=bool))
