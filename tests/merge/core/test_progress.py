"""Where a merge is, and that a cancel is heard in every stage (``merge.core.progress``)."""

from __future__ import annotations

import numpy as np
import pytest

from merge import MergeCancelled, Status, run
from merge.core.progress import SHARES, Tracker, checkpoint, stage, tracking
from tests.conftest import Synthetic


def test_a_merge_tells_every_stage_in_order_and_ends_done(small_mosaic: Synthetic) -> None:
    said: list[Status] = []
    run(small_mosaic.patch_set, status=said.append)
    stages = [s.stage for s in said]
    assert [name for name in SHARES if name in stages] == list(SHARES)
    # in order: a stage once left is not told again
    firsts = [stages.index(name) for name in SHARES]
    assert firsts == sorted(firsts)
    fractions = [s.fraction for s in said]
    assert fractions == sorted(fractions)
    assert fractions[-1] == pytest.approx(1.0)
    assert any("level" in s.detail for s in said if s.stage == "refine")


@pytest.mark.parametrize("where", list(SHARES))
def test_a_cancel_is_heard_in_every_stage(small_mosaic: Synthetic, where: str) -> None:
    seen: list[str] = []

    def cancel() -> bool:
        return bool(seen) and seen[-1] == where

    with pytest.raises(MergeCancelled):
        run(small_mosaic.patch_set, status=lambda s: seen.append(s.stage), cancel=cancel)
    assert seen[-1] == where


def test_the_eta_follows_the_pace() -> None:
    now = [0.0]
    said: list[Status] = []
    tracker = Tracker(said.append, None, clock=lambda: now[0])
    tracker.enter("start", 10)
    now[0] = 12.0
    tracker.advance(10)  # the start done: 24 % of the merge in 12 s
    assert said[-1].fraction == pytest.approx(SHARES["start"])
    assert said[-1].eta == pytest.approx(12.0 * (1 - 0.24) / 0.24)
    assert Status("start", "", 0.0, 0.0).eta is None


def test_outside_a_merge_checkpoints_do_nothing() -> None:
    with stage("start", 3):
        checkpoint(1)
    with tracking(None, lambda: True), pytest.raises(MergeCancelled):
        checkpoint()


def test_an_unknown_stage_is_refused() -> None:
    with (
        tracking(lambda s: None, None),
        pytest.raises(ValueError, match="stage must be"),
        stage("polish"),
    ):
        pass


def test_the_result_of_a_tracked_merge_is_the_untracked_one(small_mosaic: Synthetic) -> None:
    quiet = run(small_mosaic.patch_set)
    told = run(small_mosaic.patch_set, status=lambda s: None, cancel=lambda: False)
    np.testing.assert_array_equal(quiet.mosaic.heights, told.mosaic.heights)
