"""Scoring a merge against the truth of a synthetic patch set (``backend.synthetic``)."""

from __future__ import annotations

import numpy as np
import pytest

from backend.synthetic import registration_error
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
