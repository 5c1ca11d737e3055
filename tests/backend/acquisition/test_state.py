from __future__ import annotations

import logging

import pytest

from backend.acquisition.state import (
    PATCH_TRANSITIONS,
    RUN_TRANSITIONS,
    PatchStep,
    RunState,
    Transition,
    TransitionError,
    patch_machine,
    run_machine,
)


def test_a_run_from_plan_to_completion_is_observed_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    seen: list[Transition[RunState]] = []
    run = run_machine("run 1", RunState.PLANNED, seen.append)
    with caplog.at_level(logging.INFO, logger="mosaic_afm.acquisition"):
        run.go(RunState.RUNNING, actor="operator", reason="start")
        run.go(RunState.PAUSED, actor="operator")
        run.go(RunState.RUNNING)
        run.go(RunState.COMPLETED)
    assert [t.target for t in seen] == [
        RunState.RUNNING,
        RunState.PAUSED,
        RunState.RUNNING,
        RunState.COMPLETED,
    ]
    assert seen[0].actor == "operator"
    assert "run 1: planned -> running (operator: start)" in caplog.text


@pytest.mark.parametrize(
    ("source", "target"),
    [
        (RunState.COMPLETED, RunState.RUNNING),
        (RunState.ABORTED, RunState.RUNNING),
        (RunState.PLANNED, RunState.PAUSED),
        (RunState.FAULT, RunState.RUNNING),  # only an operator reset leaves a fault
        (RunState.PAUSED, RunState.COMPLETED),
    ],
)
def test_illegal_run_transitions_raise(source: RunState, target: RunState) -> None:
    seen: list[Transition[RunState]] = []
    run = run_machine("run 2", source, seen.append)
    with pytest.raises(TransitionError, match=f"from '{source.value}' to '{target.value}'"):
        run.go(target)
    assert run.state is source
    assert seen == []


def test_failed_and_interrupted_runs_resume_and_a_fault_needs_a_reset() -> None:
    for state in (RunState.FAILED, RunState.INTERRUPTED):
        assert run_machine("r", state).can(RunState.RUNNING)
    fault = run_machine("r", RunState.FAULT)
    assert RUN_TRANSITIONS[RunState.FAULT] == {RunState.FAILED}
    fault.go(RunState.FAILED, actor="operator", reason="tip checked retracted")
    assert fault.can(RunState.RUNNING)


def test_patch_steps_go_in_order_and_a_fault_returns_to_pending() -> None:
    patch = patch_machine("run 1 patch 3", PatchStep.PENDING)
    for step in (
        PatchStep.MOVE,
        PatchStep.LAND,
        PatchStep.SCAN,
        PatchStep.RETRACT,
        PatchStep.STORED,
    ):
        patch.go(step)
    with pytest.raises(TransitionError, match="pending"):
        patch.go(PatchStep.MOVE)  # a stored patch is scanned again only through pending
    patch.go(PatchStep.PENDING, reason="re-scan: the quality gate failed it")
    again = patch_machine("run 1 patch 4", PatchStep.LAND)
    again.go(PatchStep.PENDING, reason="no surface")
    with pytest.raises(TransitionError):
        again.go(PatchStep.SCAN)  # never scan without moving and landing first


def test_every_state_has_a_row_and_targets_exist() -> None:
    for table, enum in ((RUN_TRANSITIONS, RunState), (PATCH_TRANSITIONS, PatchStep)):
        assert set(table) == set(enum)
        for targets in table.values():
            assert targets <= set(enum)
