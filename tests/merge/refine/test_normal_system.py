"""The Gauss-Newton system: a build that does not depend on its blocking."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import coo_matrix

from merge.refine import normal_system as ns
from merge.refine.lines import OffsetRatios
from merge.refine.normal_system import build_normal_system
from merge.refine.slope_widths import choose_source_slopes
from tests.merge.refine.test_rows import four_patches
from tests.merge.refine.test_slope_widths import overlapping_pair


@pytest.mark.parametrize("block_rows", [1, 97, 1000])
def test_the_system_does_not_depend_on_its_blocks(block_rows: int) -> None:
    bank, state = four_patches()
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


def test_lines_shared_between_runs_enter_the_system_through_the_runs_relative_unknowns() -> None:
    # every run sees y_k = x_src - T_k' x_dst; the system's quadratic form must be the runs'
    # blocks and the blocks their shared lines put between two runs of one source, on those y
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    cand = bank.candidates(pairs, state.R, state.s, 1.5)
    blocks = cand.blocks(1000)
    rows = ns._scored_rows(bank, cand, state, 0.1, blocks)
    assert rows is not None
    info = ns._run_information(bank, cand, state, rows, blocks, OffsetRatios(3.0, 2.0))
    shared = info.shared
    assert len(shared.first) > 0
    assert (cand.src[shared.first] == cand.src[shared.second]).all()  # runs of one source
    a_rows, a_cols, vals, g, _ = ns._assemble(
        bank, state, cand.src, cand.dst, info.Baa, info.ga, shared
    )
    n = len(bank.centre)
    A = coo_matrix((vals, (a_rows, a_cols)), shape=(6 * n, 6 * n)).toarray()
    T = ns.relative_maps(bank, state, cand.src, cand.dst)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x = rng.normal(size=(n, 6))
        y = x[cand.src] - np.einsum("kji,kj->ki", T, x[cand.dst])
        form = np.einsum("ki,kij,kj->", y, info.Baa, y)
        form -= 2.0 * np.einsum("pi,pij,pj->", y[shared.first], shared.C, y[shared.second])
        assert x.ravel() @ A @ x.ravel() == pytest.approx(form, rel=1e-10)
        assert x.ravel() @ g.ravel() == pytest.approx(-np.sum(info.ga * y), rel=1e-10)
