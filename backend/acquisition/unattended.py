"""The instrument with no run driving it: recovery when the server starts again, and the
supervisor between runs. Mixed into :class:`backend.acquisition.runner.Runner`.

A server killed mid-run leaves its run active in the database and perhaps the tip down:
:meth:`UnattendedSafety.recover` makes the instrument safe first, marks such runs
``interrupted`` (resumable) and their unfinished patches pending, and reconciles every run's
file with its rows; a file that cannot be opened is moved aside into ``quarantine/`` and its
run marked ``damaged``. Between runs the supervisor records the ends a full disk refused once
there is room, and makes the instrument safe when it finds the tip down with nobody scanning.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from backend.acquisition.state import ACTIVE, PatchStep, RunState
from backend.db.models import Run
from backend.db.patch_store import reconcile
from backend.events import EventBus
from hardware.microscope import Microscope

log = logging.getLogger("mosaic_afm.runner")


class UnattendedSafety:
    """Recovery and supervision (the runner holds the attributes and methods declared here)."""

    microscope: Microscope
    sessions: sessionmaker[Session]
    events: EventBus
    data_dir: Path
    _io: threading.Lock
    _stopping: threading.Event
    _supervisor: threading.Thread | None

    if TYPE_CHECKING:  # the runner's own (and its mixins'), for the type checker

        @property
        def active_run(self) -> int | None: ...

        def _try_safe_state(self) -> str | None: ...

        def flush(self) -> None: ...

        def _transition(
            self, session: Session, run: Run, target: RunState, reason: str, actor: str
        ) -> None: ...

    def recover(self) -> list[str]:
        """After a (re)start: runs that were active become ``interrupted``; every run's file
        and rows are reconciled. Return what was done."""
        notes: list[str] = []
        with self.sessions() as session:
            runs = session.scalars(select(Run).order_by(Run.id)).all()
            if any(RunState(run.state) in ACTIVE for run in runs):
                # the server died mid-run: whatever the tip was doing, it stops now
                problem = self._try_safe_state()
                notes.append(problem or "the instrument was put in its safe state")
            for run in runs:
                if RunState(run.state) in ACTIVE:
                    reason = "the server stopped during the run; resume to continue"
                    self._transition(session, run, RunState.INTERRUPTED, reason, "server")
                    notes.append(f"run {run.id}: interrupted")
                for patch in run.patches:
                    if patch.step not in (PatchStep.PENDING.value, PatchStep.STORED.value):
                        patch.step = PatchStep.PENDING.value
                session.commit()
                try:
                    notes.extend(f"run {run.id}: {n}" for n in reconcile(session, run))
                except (OSError, KeyError, ValueError, RuntimeError) as exc:
                    session.rollback()
                    notes.append(f"run {run.id}: {self._quarantine(session, run, exc)}")
        for note in notes:
            self.events.emit("recovery", note, data={})
        return notes

    def _quarantine(self, session: Session, run: Run, exc: BaseException) -> str:
        """Move a run file that cannot be opened aside and mark its run ``damaged``."""
        source = run.file
        aside = self.data_dir / "quarantine" / f"{source.name}.{int(time.time())}"
        aside.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(source, aside)
        reason = (
            f"its file {source.name} could not be opened ({type(exc).__name__}: "
            f"{str(exc)[:200]}); moved to {aside.relative_to(self.data_dir)}"
        )
        log.error("run %s: %s", run.id, reason)
        if RunState(run.state) == RunState.FAULT:  # it still blocks until an operator's reset
            return f"in fault, and {reason}"
        self._transition(session, run, RunState.DAMAGED, reason, "server")
        return f"damaged: {reason}"

    def start_supervisor(self, interval: float = 1.0) -> None:
        """Watch the instrument while no run does: record ends the disk refused once it has
        room again, and make the instrument safe if the tip is down with nobody scanning."""
        if self._supervisor is None:
            self._supervisor = threading.Thread(
                target=self._supervise, args=(interval,), name="supervisor", daemon=True
            )
            self._supervisor.start()

    def _supervise(self, interval: float) -> None:
        while not self._stopping.wait(interval):
            try:
                self.flush()
                self._watch_instrument()
            except Exception:  # the supervisor keeps watching
                log.exception("supervisor: check failed")

    def _watch_instrument(self) -> None:
        loop = self.microscope.loop
        if loop is None or self.active_run is not None or not self._io.acquire(timeout=0):
            return
        try:
            if self.active_run is None and loop.engaged():
                problem = self._try_safe_state()
                message = "the tip was down with no run scanning: " + (
                    problem or "the instrument is now in its safe state"
                )
                log.error("supervisor: %s", message)
                self.events.publish(
                    "fault", message, data={"state": "safe" if not problem else "fault"}
                )
        finally:
            self._io.release()
