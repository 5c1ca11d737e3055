"""Each patch's slope smoothing, chosen by how well its slopes match its neighbours'."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from merge.core.patchset import Patch
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState
from merge.refine.runs import Runs
from merge.refine.slope_widths import WIDTHS, choose_source_slopes
from merge.refine.source_slopes import SourceSlopes, gaussian_slope_noise


def overlapping_pair(
    surface: np.ndarray, noise: float, seed: int
) -> tuple[SurfaceBank, PatchState]:
    """Two 110 px wide patches of ``surface`` (120 x 200 px), 20 px of overlap, each with its
    own white noise, at their true places (1 m pixels)."""
    rng = np.random.default_rng(seed)
    patches = [
        Patch(
            id=str(k),
            heights=surface[:, 90 * k : 90 * k + 110] + rng.normal(0.0, noise, (120, 110)),
            origin=(90.0 * k, 0.0),
            pixel_size=(1.0, 1.0),
        )
        for k in range(2)
    ]
    bank = SurfaceBank(patches, 1.0, 0.0, 1)
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    return bank, PatchState(R, bank.centre.copy(), np.zeros((2, 2)))


def _choose(bank: SurfaceBank, state: PatchState) -> SourceSlopes | None:
    runs = bank.candidates(np.array([[0, 1]]), state.R, state.s, 1.5)
    return choose_source_slopes(bank, runs, state)


def test_a_smooth_face_under_noise_chooses_smoothing_and_says_how_much_noise_it_left() -> None:
    # smooth at the pixel scale (correlation 8 px) under noise as strong as its slopes
    rng = np.random.default_rng(1)
    surface = ndimage.gaussian_filter(rng.normal(size=(120, 200)), 8.0) * 40.0
    bank, state = overlapping_pair(surface, 0.3, 2)
    slopes = _choose(bank, state)
    assert slopes is not None
    assert set(slopes.grids) == {0, 1}
    assert slopes.width in WIDTHS
    assert slopes.spread2 > 0
    assert slopes.noise_ratio == pytest.approx(
        gaussian_slope_noise(slopes.width) / bank.slope_noise
    )
    assert slopes.noise_ratio < 0.2
    for c in (0, 1):
        assert slopes.grids[c].shape == (120, 110, 2)


def test_roughness_at_the_pixel_scale_keeps_the_look_ups() -> None:
    # every pixel its own texture, faint noise: smoothing would take signal, not noise
    rng = np.random.default_rng(3)
    bank, state = overlapping_pair(rng.normal(size=(120, 200)), 0.05, 4)
    slopes = _choose(bank, state)
    assert slopes is None


def test_the_choice_needs_the_raw_look_ups_of_its_own_bank() -> None:
    rng = np.random.default_rng(5)
    surface = ndimage.gaussian_filter(rng.normal(size=(120, 200)), 8.0) * 40.0
    bank, state = overlapping_pair(surface, 0.3, 6)
    bank.source_slopes = _choose(bank, state)
    assert bank.source_slopes is not None
    with pytest.raises(ValueError, match="look-ups"):
        _choose(bank, state)
    patches = [Patch("a", surface[:, :110], (0.0, 0.0), (1.0, 1.0))]
    with pytest.raises(ValueError, match="raw heights"):
        choose_source_slopes(SurfaceBank(patches, 1.0, 1.0, 1), Runs.empty(), state)
