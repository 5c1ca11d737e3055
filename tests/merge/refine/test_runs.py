"""The rows of the system, run by run: how they are cut into blocks, and where the blocks are
worked."""

from __future__ import annotations

import numpy as np
import pytest

from merge.core import parallel
from merge.refine import runs
from merge.refine.runs import BlockPlan, Runs, block_plan


def test_blocks_keep_a_sources_runs_together() -> None:
    # sources 0, 0, 1, 2, 2 with 10 rows a run: blocks of about 15 rows
    starts = np.arange(0, 60, 10)
    r = Runs(
        np.array([0, 0, 1, 2, 2]),
        np.array([1, 2, 0, 0, 1]),
        np.zeros((5, 4), dtype=np.intp),
        starts,
    )
    assert r.blocks(15) == [(0, 2), (2, 3), (3, 5)]
    assert r.blocks(10**6) == [(0, 5)]


def test_blocks_are_shared_among_the_cores_only_where_they_are_large(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(parallel, "WORKERS", 2)
    large = runs.SHARED_BLOCK_ROWS * runs.PIXELS_PER_BLOCK_ROW
    assert block_plan(large) == BlockPlan(runs.SHARED_BLOCK_ROWS, True)
    assert block_plan(100 * large) == BlockPlan(runs.BLOCK_ROWS, True)
    # below, one core works the blocks both would have held at once
    assert block_plan(large - runs.PIXELS_PER_BLOCK_ROW) == BlockPlan(
        2 * (runs.SHARED_BLOCK_ROWS - 1), False
    )
    assert block_plan(1000) == BlockPlan(runs.LEAST_BLOCK_ROWS, False)
    monkeypatch.setattr(parallel, "WORKERS", 1)
    assert block_plan(100 * large) == BlockPlan(runs.BLOCK_ROWS, False)
