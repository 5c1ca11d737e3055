"""The system's assembly from its runs' blocks, and the blocks shared lines put between runs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix

from merge.refine import normal_system as ns
from merge.refine.assembly import assemble, relative_maps
from merge.refine.lines import OffsetRatios
from tests.merge.refine.test_rows import four_patches


def test_lines_shared_between_runs_enter_the_system_through_the_runs_relative_unknowns() -> None:
    # every run sees y_k = x_src - T_k' x_dst; the system's quadratic form must be the runs'
    # blocks and the blocks their shared lines put between two runs of one source, on those y
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    cand = bank.candidates(pairs, state.R, state.s, 1.5)
    blocks = cand.blocks(1000)
    rows = ns._scored_rows(bank, cand, state, 0.1, blocks, False)
    assert rows is not None
    info = ns._run_information(bank, cand, state, rows, blocks, OffsetRatios(3.0, 2.0))
    shared = info.shared
    assert len(shared.first) > 0
    assert (cand.src[shared.first] == cand.src[shared.second]).all()  # runs of one source
    a_rows, a_cols, vals, g, _ = assemble(
        bank, state, cand.src, cand.dst, info.Baa, info.ga, shared
    )
    n = len(bank.centre)
    A = coo_matrix((vals, (a_rows, a_cols)), shape=(6 * n, 6 * n)).toarray()
    T = relative_maps(bank, state, cand.src, cand.dst)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x = rng.normal(size=(n, 6))
        y = x[cand.src] - np.einsum("kji,kj->ki", T, x[cand.dst])
        form = np.einsum("ki,kij,kj->", y, info.Baa, y)
        form -= 2.0 * np.einsum("pi,pij,pj->", y[shared.first], shared.C, y[shared.second])
        assert x.ravel() @ A @ x.ravel() == pytest.approx(form, rel=1e-10)
        assert x.ravel() @ g.ravel() == pytest.approx(-np.sum(info.ga * y), rel=1e-10)
