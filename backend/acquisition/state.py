"""The acquisition state machine: one explicit transition table for runs and for patches.

Run states (docs/design.md): ``planned -> running -> (paused) -> completed | aborted | failed``, and
``interrupted`` when the server stops mid-run. A failed or interrupted run resumes from the
first patch not stored. ``fault`` is the blocking state of a run whose safe state (tip
retracted, axes stopped) could not be confirmed: only an operator's reset leaves it, to
``failed``.

Patch steps, in order: ``pending -> move -> land -> scan -> retract -> stored``; a fault during
a step sends the patch back to ``pending`` (a patch whose data is not stored was not scanned).

Every transition is checked against the tables, logged, and handed to an observer (which
writes it to the database before the next step starts). An illegal one raises
:class:`TransitionError` (HTTP 409 at the API).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Generic, TypeVar

log = logging.getLogger("mosaic_afm.acquisition")


class RunState(StrEnum):
    PLANNED = "planned"
    RUNNING = "running"
    PAUSED = "paused"
    COMPLETED = "completed"
    ABORTED = "aborted"
    FAILED = "failed"
    INTERRUPTED = "interrupted"
    FAULT = "fault"
    #: its file could not be opened at start-up: moved aside, the run kept for the record
    DAMAGED = "damaged"


class PatchStep(StrEnum):
    PENDING = "pending"
    MOVE = "move"
    LAND = "land"
    SCAN = "scan"
    RETRACT = "retract"
    STORED = "stored"


_DAMAGED = frozenset({RunState.DAMAGED})  # found at start-up, from a state at rest

RUN_TRANSITIONS: Mapping[RunState, frozenset[RunState]] = {
    RunState.PLANNED: frozenset({RunState.RUNNING, RunState.ABORTED}) | _DAMAGED,
    RunState.RUNNING: frozenset(
        {
            RunState.PAUSED,
            RunState.COMPLETED,
            RunState.ABORTED,
            RunState.FAILED,
            RunState.INTERRUPTED,
            RunState.FAULT,
        }
    ),
    RunState.PAUSED: frozenset(
        {RunState.RUNNING, RunState.ABORTED, RunState.INTERRUPTED, RunState.FAULT}
    ),
    RunState.FAILED: frozenset({RunState.RUNNING, RunState.ABORTED}) | _DAMAGED,
    RunState.INTERRUPTED: frozenset({RunState.RUNNING, RunState.ABORTED}) | _DAMAGED,
    RunState.FAULT: frozenset({RunState.FAILED}),  # only an operator's reset: it blocks
    RunState.COMPLETED: _DAMAGED,
    RunState.ABORTED: _DAMAGED,
    RunState.DAMAGED: frozenset(),
}

PATCH_TRANSITIONS: Mapping[PatchStep, frozenset[PatchStep]] = {
    PatchStep.PENDING: frozenset({PatchStep.MOVE}),
    PatchStep.MOVE: frozenset({PatchStep.LAND, PatchStep.PENDING}),
    PatchStep.LAND: frozenset({PatchStep.SCAN, PatchStep.PENDING}),
    PatchStep.SCAN: frozenset({PatchStep.RETRACT, PatchStep.PENDING}),
    PatchStep.RETRACT: frozenset({PatchStep.STORED, PatchStep.PENDING}),
    # a re-scan: the quality gate (or the operator) failed the stored patch
    PatchStep.STORED: frozenset({PatchStep.PENDING}),
}

#: Run states from which a run can (re)start.
STARTABLE = frozenset({RunState.PLANNED, RunState.FAILED, RunState.INTERRUPTED})
#: Run states in which the instrument is in use.
ACTIVE = frozenset({RunState.RUNNING, RunState.PAUSED})

S = TypeVar("S", RunState, PatchStep)


class TransitionError(RuntimeError):
    """A transition the table does not allow; the message names both states and what is
    allowed instead."""

    def __init__(
        self, what: str, current: StrEnum, target: StrEnum, allowed: frozenset[StrEnum]
    ) -> None:
        self.current, self.target = current, target
        options = ", ".join(sorted(s.value for s in allowed)) or "nothing (final state)"
        super().__init__(
            f"{what} cannot go from {current.value!r} to {target.value!r}; allowed: {options}"
        )


@dataclass(frozen=True)
class Transition(Generic[S]):
    """One transition, as observers receive it."""

    subject: str
    source: S
    target: S
    reason: str
    actor: str


class StateMachine(Generic[S]):
    """The state of one run or one patch, changed only through :meth:`go`.

    Parameters
    ----------
    subject : str
        What this is the state of, for messages and logs ("run 3", "run 3 patch 12").
    state : RunState or PatchStep
        The current state (as stored).
    table : mapping
        :data:`RUN_TRANSITIONS` or :data:`PATCH_TRANSITIONS`.
    observer : callable, optional
        Called with every :class:`Transition` before :meth:`go` returns (persist it there).
    """

    def __init__(
        self,
        subject: str,
        state: S,
        table: Mapping[S, frozenset[S]],
        observer: Callable[[Transition[S]], None] | None = None,
    ) -> None:
        if state not in table:
            raise ValueError(f"{subject}: unknown state {state!r}")
        self.subject = subject
        self.state: S = state
        self.table: Mapping[S, frozenset[S]] = table
        self.observer: Callable[[Transition[S]], None] | None = observer

    def can(self, target: S) -> bool:
        return target in self.table[self.state]

    def go(self, target: S, *, reason: str = "", actor: str = "system") -> Transition[S]:
        """Move to ``target`` or raise :class:`TransitionError`; log and observe it."""
        allowed = self.table[self.state]
        if target not in allowed:
            raise TransitionError(self.subject, self.state, target, frozenset(allowed))
        change = Transition(self.subject, self.state, target, reason, actor)
        if self.observer is not None:
            self.observer(change)  # persisted before the state changes in memory
        log.info(
            "%s: %s -> %s (%s%s)",
            self.subject,
            change.source.value,
            target.value,
            actor,
            f": {reason}" if reason else "",
        )
        self.state = target
        return change


def run_machine(
    subject: str, state: RunState, observer: Callable[[Transition[RunState]], None] | None = None
) -> StateMachine[RunState]:
    return StateMachine(subject, state, RUN_TRANSITIONS, observer)


def patch_machine(
    subject: str,
    state: PatchStep,
    observer: Callable[[Transition[PatchStep]], None] | None = None,
) -> StateMachine[PatchStep]:
    return StateMachine(subject, state, PATCH_TRANSITIONS, observer)
