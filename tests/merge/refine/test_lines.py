"""Scan lines as correlated noise: groups, the offset ratio, the marginalised sums."""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest
from numpy.typing import NDArray

from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import Chessboard
from merge import PatchTransform
from merge.refine import normal_system as ns
from merge.refine.icp import DEFAULT_LEVELS, refine
from merge.refine.lines import (
    OffsetRatios,
    group_sums,
    marginalise_offsets,
    offset_ratio,
    ratio_of_sums,
    shared_ratios,
)
from tests.conftest import make_synthetic

FloatArray = NDArray[np.float64]


def _grouped(
    rng: np.random.Generator, groups: int, size: int, sigma: float, tau: float
) -> tuple[FloatArray, FloatArray]:
    """Residuals of ``groups`` lines of ``size`` rows: white ``sigma`` plus one offset ``tau``
    per line; and the first row of every line."""
    r = rng.normal(0.0, sigma, (groups, size)) + rng.normal(0.0, tau, (groups, 1))
    return r.ravel(), np.arange(groups) * size


def test_the_groups_sums_of_blocks_give_the_ratio_of_the_whole() -> None:
    # a mosaic's groups are summed block by block; the ratio must not see the blocks
    rng = np.random.default_rng(4)
    r, first = _grouped(rng, 600, 12, 1.0, 0.3)
    w = rng.uniform(0.2, 1.0, r.size)
    ones = np.ones_like(r)
    parts = [
        group_sums(r[lo:hi], w[lo:hi], ones[lo:hi], first[(first >= lo) & (first < hi)] - lo)
        for lo, hi in pairwise([0, 12 * 100, 12 * 450, r.size])
    ]
    whole = offset_ratio(r, w, ones, first)
    assert np.isfinite(whole)
    assert ratio_of_sums(np.concatenate(parts, axis=1)) == pytest.approx(whole, rel=1e-12)


def test_the_offset_ratio_is_white_over_line_variance() -> None:
    rng = np.random.default_rng(0)
    r, first = _grouped(rng, 2000, 15, 1.0, 0.3)
    ones = np.ones_like(r)
    assert offset_ratio(r, ones, ones, first) == pytest.approx(1.0 / 0.09, rel=0.15)


def test_without_line_offsets_the_ratio_is_huge_or_infinite() -> None:
    rng = np.random.default_rng(1)
    r, first = _grouped(rng, 2000, 15, 1.0, 0.0)
    ones = np.ones_like(r)
    assert offset_ratio(r, ones, ones, first) > 100.0


def test_a_few_far_out_lines_do_not_pass_for_offsets() -> None:
    # a misfit or a defect puts some lines' means far out; the median does not follow them
    rng = np.random.default_rng(2)
    r, first = _grouped(rng, 2000, 15, 1.0, 0.3)
    r = r.reshape(2000, 15)
    r[:100] += 20.0
    ones = np.ones(r.size)
    assert offset_ratio(r.ravel(), ones, ones, first) == pytest.approx(1.0 / 0.09, rel=0.3)


def test_marginalised_sums_are_generalised_least_squares() -> None:
    rng = np.random.default_rng(3)
    m = 40
    J, r, w = rng.normal(size=(m, 6)), rng.normal(size=m), rng.uniform(0.2, 1.0, m)
    runs = np.array([0, 17, 40])
    first = np.array([0, 5, 11, 17, 30])  # every run starts a group
    rho = 4.0
    B = np.stack([(J[a:b] * w[a:b, None]).T @ J[a:b] for a, b in pairwise(runs)])
    g = np.stack([(w[a:b] * r[a:b]) @ J[a:b] for a, b in pairwise(runs)])
    marginalise_offsets(J, w, r, runs, first, OffsetRatios(rho, np.inf), B, g)
    # the inverse covariance of a group, in units of the white variance: W - W 1 1' W / (ρ + Σ w)
    bounds = [*first.tolist(), m]
    inv = np.zeros((m, m))
    for a, b in pairwise(bounds):
        W = np.diag(w[a:b])
        inv[a:b, a:b] = W - W @ np.ones((b - a, b - a)) @ W / (rho + w[a:b].sum())
    for k, (a, b) in enumerate(pairwise(runs)):
        np.testing.assert_allclose(B[k], J[a:b].T @ inv[a:b, a:b] @ J[a:b], atol=1e-12)
        np.testing.assert_allclose(g[k], J[a:b].T @ inv[a:b, a:b] @ r[a:b], atol=1e-12)


def test_an_infinite_ratio_leaves_the_sums_alone() -> None:
    B, g = np.ones((1, 6, 6)), np.ones((1, 6))
    J = np.ones((3, 6))
    none = OffsetRatios(np.inf, np.inf)
    marginalise_offsets(J, np.ones(3), np.ones(3), np.array([0, 3]), np.array([0]), none, B, g)
    assert (B == 1).all() and (g == 1).all()


def _pair_error() -> float:
    """XY error (m) of a refined pair whose only noise is strong per-line offsets."""
    drift = DriftModel(
        stage_sigma=30e-9,
        rotation_sigma_deg=0.3,
        z_step_mean=20e-9,
        z_step_sigma=10e-9,
        z_drift_sigma=0.0,
        noise=0.02e-9,
        line_noise=1e-9,
    )
    surface = Chessboard(period=0.8e-6, step=100e-9, edge_width=100e-9, seed=3)
    syn = make_synthetic(
        surface, rows=1, cols=2, drift=drift, patch_size=(0.6e-6, 0.6e-6), pixels=(30, 30)
    )
    truth = [PatchTransform(s.rotation, s.translation) for s in syn.synth]
    fit = refine(syn.patch_set.patches, np.array([[0, 1]]), truth, levels=DEFAULT_LEVELS[-1:])
    return syn.registration_error(fit.transforms)[0]


def test_line_offsets_do_not_drag_a_pair_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    # a line whose ends lie at different heights (across an edge) drags XY with its offset when
    # its residuals count as independent; marginalised, only the within-line variation measures
    # (here 0.07 nm against 0.22 nm)
    with_lines = _pair_error()
    monkeypatch.setattr(ns, "shared_ratios", lambda *args: OffsetRatios(np.inf, np.inf))
    without = _pair_error()
    assert with_lines < 0.5 * without


def test_shared_line_offsets_are_generalised_least_squares_across_runs() -> None:
    # two nested offsets: one per group (its run's own) and one per line shared by its runs;
    # the runs' blocks and the blocks between runs are those of the whole GLS in the runs'
    # relative unknowns (6 per run)
    rng = np.random.default_rng(5)
    runs = np.array([0, 12, 30, 41])
    first = np.array([0, 4, 8, 12, 18, 24, 30, 35])  # every run starts a group
    lines = np.array([7, 8, 9, 7, 8, 9, 8, 9])  # lines 8 and 9 in all three runs, 7 in two
    m, k = runs[-1], len(runs) - 1
    J, r, w = rng.normal(size=(m, 6)), rng.normal(size=m), rng.uniform(0.2, 1.0, m)
    rho = OffsetRatios(run=3.0, line=2.0)
    B = np.stack([(J[a:b] * w[a:b, None]).T @ J[a:b] for a, b in pairwise(runs)])
    g = np.stack([(w[a:b] * r[a:b]) @ J[a:b] for a, b in pairwise(runs)])
    between = marginalise_offsets(J, w, r, runs, first, rho, B, g, lines)
    # dense: covariance W^-1 + Z Z' / ρ_run + L L' / ρ_line over the rows, unknowns y (6 k)
    group = np.repeat(np.arange(len(first)), np.diff([*first.tolist(), m]))
    Z = np.eye(len(first))[group]
    L = (lines[group][:, None] == np.unique(lines)[None, :]).astype(float)
    inv = np.linalg.inv(np.diag(1.0 / w) + Z @ Z.T / rho.run + L @ L.T / rho.line)
    run = np.repeat(np.arange(k), np.diff(runs))
    Y = np.zeros((m, 6 * k))
    for row in range(m):
        Y[row, 6 * run[row] : 6 * run[row] + 6] = J[row]
    A, grad = Y.T @ inv @ Y, Y.T @ inv @ r
    for q in range(k):
        np.testing.assert_allclose(B[q], A[6 * q : 6 * q + 6, 6 * q : 6 * q + 6], atol=1e-12)
        np.testing.assert_allclose(g[q], grad[6 * q : 6 * q + 6], atol=1e-12)
    pairs = zip(between.first.tolist(), between.second.tolist(), strict=True)
    assert sorted(pairs) == [(0, 1), (0, 2), (1, 2)]
    for a, b, C in zip(between.first, between.second, between.C, strict=True):
        np.testing.assert_allclose(-C, A[6 * a : 6 * a + 6, 6 * b : 6 * b + 6], atol=1e-12)


def test_shared_ratios_split_a_groups_offset_into_its_lines_and_its_runs() -> None:
    # every line met by three runs side by side (columns apart): a shared offset of 0.4 and a
    # run's own of 0.3 on white noise of 1
    rng = np.random.default_rng(6)
    lines, runs, size = 3000, 3, 12
    shared = rng.normal(0.0, 0.4, (lines, 1, 1))
    own = rng.normal(0.0, 0.3, (lines, runs, 1))
    r = (rng.normal(0.0, 1.0, (lines, runs, size)) + shared + own).ravel()
    first = np.arange(lines * runs) * size
    ones = np.ones_like(r)
    sums = group_sums(r, ones, ones, first)
    which = np.repeat(np.arange(lines), runs)
    left = np.tile(np.arange(runs) * 20, lines)
    spans = np.column_stack([left, left + size])
    ratios = shared_ratios(sums, which, spans)
    assert 1.0 / ratios.line == pytest.approx(0.16, rel=0.2)
    assert 1.0 / ratios.run == pytest.approx(0.09, rel=0.3)
    # where the runs of a line share their points, their differences say nothing of offsets
    one_place = np.column_stack([np.zeros_like(left), np.full_like(left, size)])
    overlapping = shared_ratios(sums, which, one_place)
    assert np.isinf(overlapping.line)
    assert 1.0 / overlapping.run == pytest.approx(0.25, rel=0.2)
