"""State machines whose every transition is committed to the database and published as an
event before it takes effect (docs/design.md: written before the next step starts)."""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy.orm import Session

from backend.acquisition.state import (
    PatchStep,
    RunState,
    StateMachine,
    Transition,
    patch_machine,
    run_machine,
)
from backend.db.models import PatchRecord, Run
from backend.events import EventBus


def journaled_run(session: Session, events: EventBus, run: Run) -> StateMachine[RunState]:
    """The run's state machine; a transition sets ``state`` and ``message`` (why, and who
    asked), commits, and emits a ``run`` event."""

    def persist(change: Transition[RunState]) -> None:
        run.state = change.target.value
        run.message = f"{change.reason} ({change.actor})" if change.reason else None
        session.commit()
        events.emit(
            "run",
            f"run {run.id}: {change.source.value} -> {change.target.value}"
            + (f" ({change.actor}: {change.reason})" if change.reason else ""),
            run_id=run.id,
            data={
                "state": change.target.value,
                "from": change.source.value,
                "reason": change.reason,
                "actor": change.actor,
            },
        )

    return run_machine(f"run {run.id}", RunState(run.state), observer=persist)


def journaled_patch(
    session: Session, events: EventBus, run: Run, patch: PatchRecord
) -> StateMachine[PatchStep]:
    """A patch's step machine; a transition sets ``step`` (and ``stored_at``), commits, and
    emits a ``patch`` event."""

    def persist(change: Transition[PatchStep]) -> None:
        patch.step = change.target.value
        if change.target == PatchStep.STORED:
            patch.stored_at = datetime.now(UTC)
        session.commit()
        events.emit(
            "patch",
            f"run {run.id} patch {patch.index}: {change.target.value}",
            run_id=run.id,
            data={"patch": patch.index, "step": change.target.value, "from": change.source.value},
        )

    return patch_machine(
        f"run {run.id} patch {patch.index}", PatchStep(patch.step), observer=persist
    )
