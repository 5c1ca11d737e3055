"""The Gauss-Newton system: a build that does not depend on its blocking."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from merge.core import parallel
from merge.refine import runs
from merge.refine.normal_system import build_normal_system
from merge.refine.runs import block_plan
from merge.refine.slope_widths import choose_source_slopes
from tests.merge.refine.test_rows import four_patches
from tests.merge.refine.test_slope_widths import overlapping_pair


@pytest.mark.parametrize("on_cores", [False, True])
@pytest.mark.parametrize("block_rows", [1, 97, 1000])
def test_the_system_does_not_depend_on_its_blocks(
    block_rows: int, on_cores: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(parallel, "WORKERS", 2)
    if on_cores:  # these patches' blocks are small: shared among the cores all the same
        monkeypatch.setattr(runs, "SHARED_BLOCK_ROWS", 0)
    bank, state = four_patches()
    assert block_plan(int(np.dot(bank.nx, bank.ny))).on_cores == on_cores
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    cand = bank.candidates(pairs, state.R, state.s, 1.5)
    whole = build_normal_system(bank, cand, state, 0.1, block_rows=10**9, signal=True)
    split = build_normal_system(bank, cand, state, 0.1, block_rows=block_rows, signal=True)
    assert whole.rms > 0 and whole.count.sum() > 0
    assert whole.signal_vals is not None and split.signal_vals is not None
    np.testing.assert_allclose(split.g, whole.g, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(split.diag, whole.diag, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(split.signal_vals, whole.signal_vals, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(split.count, whole.count)
    assert split.rscale == whole.rscale
    assert split.rms == pytest.approx(whole.rms, rel=1e-12)
    assert split.line_design == pytest.approx(whole.line_design, rel=1e-12)


def test_no_correspondence_gives_an_empty_system() -> None:
    bank, state = four_patches()
    cand = bank.candidates(np.empty((0, 2), dtype=np.intp), state.R, state.s, 1.5)
    system = build_normal_system(bank, cand, state, 0.1)
    assert system.rms == 0.0 and len(system.vals) == 0 and not system.g.any()


def test_the_per_patch_sums_come_with_the_signal_only() -> None:
    bank, state = four_patches()
    cand = bank.candidates(np.array([[0, 1], [2, 3]]), state.R, state.s, 1.5)
    steps = build_normal_system(bank, cand, state, 0.1)
    report = build_normal_system(bank, cand, state, 0.1, signal=True)
    assert not steps.count.any() and report.count.sum() > 0
    np.testing.assert_allclose(steps.g, report.g, rtol=1e-12, atol=1e-12)


def test_smoothed_slopes_claim_less_of_the_information_for_noise() -> None:
    # where the sources' smoothed slopes stand in for the look-ups, their noise is a fraction
    # of a look-up's, and the report counts each row's slopes by theirs
    rng = np.random.default_rng(1)
    surface = ndimage.gaussian_filter(rng.normal(size=(120, 200)), 8.0) * 40.0
    bank, state = overlapping_pair(surface, 0.3, 2)
    cand = bank.candidates(np.array([[0, 1]]), state.R, state.s, 1.5)
    looked_up = build_normal_system(bank, cand, state, 0.3, signal=True)
    assert looked_up.slope_count is not None
    np.testing.assert_allclose(looked_up.slope_count, looked_up.count)
    bank.source_slopes = choose_source_slopes(bank, cand, state)
    own = build_normal_system(bank, cand, state, 0.3, signal=True)
    assert own.slope_count is not None and looked_up.signal_vals is not None
    np.testing.assert_array_equal(own.count, looked_up.count)
    assert (own.slope_count < 0.8 * own.count).all()
    assert own.signal_vals is not None
    # the patches' XY information without the noise's share is nearer what the surface
    # itself holds (the same pair without noise) than the look-ups' is
    exact, at = overlapping_pair(surface, 0.0, 2)
    truth = build_normal_system(exact, cand, at, 0.3)
    place = (own.rows == own.cols) & (own.rows % 6 < 2)
    for system in (own, looked_up):
        assert np.array_equal(system.rows, truth.rows)
        assert np.array_equal(system.cols, truth.cols)
    err_own = np.abs(own.signal_vals[place] / truth.vals[place] - 1.0)
    err_looked_up = np.abs(looked_up.signal_vals[place] / truth.vals[place] - 1.0)
    assert (err_own < 0.5 * err_looked_up).all()


def test_held_weights_stand_in_for_the_rows_own_cauchy_weights() -> None:
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    cand = bank.candidates(pairs, state.R, state.s, 1.5)
    own = build_normal_system(bank, cand, state, 0.1, keep_weights=True)
    assert own.weights is not None and len(own.weights) == cand.size
    w = own.weights.astype(np.float64)  # rows whose foot misses their destination: 0
    assert (w >= 0.0).all() and 0.0 < w[w > 0].min() < w.max() <= 1.0
    # the same weights given back: the same system, to the weights' storage precision
    held = build_normal_system(bank, cand, state, 0.1, weights=own.weights)
    np.testing.assert_allclose(held.g, own.g, rtol=2e-3, atol=1e-9)
    np.testing.assert_allclose(held.diag, own.diag, rtol=2e-3, atol=1e-9)
    # held where the rows have moved, they weight the rows as they did there
    moved = replace(state, s=state.s + np.array([0.4, -0.3, 0.0]) * (np.arange(4) == 1)[:, None])
    again = build_normal_system(bank, cand, moved, 0.1, weights=own.weights, keep_weights=True)
    assert again.weights is own.weights
    fresh = build_normal_system(bank, cand, moved, 0.1)
    assert not np.allclose(again.g, fresh.g, rtol=1e-3)
    with pytest.raises(ValueError, match="one per row"):
        build_normal_system(bank, cand, state, 0.1, weights=own.weights[:-1])
