"""The end of a run: the instrument made safe first, then the end recorded, even past a disk
that refuses it for a while (the run holds its end in memory and the supervisor records it once
there is room), the live merge stopped and its last mosaic kept in the run's file. Mixed into
:class:`backend.acquisition.runner.Runner`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy.orm import Session, sessionmaker

from backend.acquisition.control import Control
from backend.acquisition.state import PatchStep, RunState, StateMachine
from backend.db.models import PatchRecord, Run
from backend.db.patch_store import LIVE_GROUP, write_mosaic
from backend.db.space import StorageFull, check_space
from backend.events import EventBus
from backend.live_merge import LiveMergeService

log = logging.getLogger("mosaic_afm.runner")


class RunEnding:
    """How a run ends (the runner holds the attributes and methods declared here)."""

    sessions: sessionmaker[Session]
    events: EventBus
    on_completed: Callable[[int], None] | None
    data_dir: Path
    reserve: int
    live: LiveMergeService | None
    _lock: threading.RLock
    _unrecorded: dict[int, tuple[RunState, str, str]]

    if TYPE_CHECKING:  # the runner's own (and its patch loop's), for the type checker

        @property
        def active_run(self) -> int | None: ...

        def _try_safe_state(self) -> str | None: ...

        def _get(self, session: Session, run_id: int) -> Run: ...

        def _patch_machine(
            self, session: Session, run: Run, patch: PatchRecord
        ) -> StateMachine[PatchStep]: ...

        def _transition(
            self, session: Session, run: Run, target: RunState, reason: str, actor: str
        ) -> None: ...

    def _conclude(
        self,
        run_id: int,
        target: RunState,
        reason: str,
        actor: str,
        *,
        safe: bool,
        control: Control | None = None,
    ) -> None:
        """Safety first, then bookkeeping: make the instrument safe (a run whose safe state
        cannot be confirmed goes to ``fault``), then record the end; where the record cannot
        be written (a full disk) the run holds that state in memory until it can."""
        if safe:
            problem = self._try_safe_state()
            if problem is not None:
                target, reason = RunState.FAULT, f"{reason}; {problem}"
        if control is not None:
            control.concluded = True  # nothing lands from now on: the status says so
        self._end_live(run_id)
        with self._lock:
            self._unrecorded[run_id] = (target, reason, actor)
        if not self._record(run_id):
            message = f"run {run_id}: {target.value} ({reason}); the database cannot record it yet"
            self.events.publish("fault", message, run_id=run_id, data={"state": target.value})
            return
        if target == RunState.COMPLETED and self.on_completed is not None:
            try:
                self.on_completed(run_id)
            except Exception:
                log.exception("run %s: starting its merge failed", run_id)

    def _end_live(self, run_id: int) -> None:
        """Stop the run's live merge and keep its last mosaic in the run's file."""
        if self.live is None:
            return
        self.live.stop(run_id)
        last = self.live.mosaic(run_id)
        if last is None:
            return
        heights, document = last
        try:
            # HDF5 must never meet a full disk (it may crash): room first, or nothing written
            check_space(self.data_dir, need=2 * heights.nbytes + (1 << 20), reserve=self.reserve)
            with self.sessions() as session:
                path = self._get(session, run_id).file
            write_mosaic(path, LIVE_GROUP, heights, document)
            self.live.forget(run_id)  # from now on read from the run's file
        except StorageFull:
            log.warning("run %s: no room to keep its live mosaic in its file", run_id)
        except Exception:  # the run's end is recorded all the same
            log.exception("run %s: keeping its live mosaic failed", run_id)

    def _record(self, run_id: int, *, attempts: int = 3, pause: float = 0.2) -> bool:
        """Write a concluded run's end to the database (retried); True once it is."""
        with self._lock:
            end = self._unrecorded.get(run_id)
        if end is None:
            return True
        target, reason, actor = end
        for attempt in range(attempts):
            try:
                with self.sessions() as session:
                    run = session.get(Run, run_id)
                    if run is not None:
                        self._finish(session, run, target, reason, actor)
                with self._lock:
                    self._unrecorded.pop(run_id, None)
                return True
            except Exception:
                log.warning("run %s: recording %s failed", run_id, target.value, exc_info=True)
                if attempt + 1 < attempts:
                    time.sleep(pause * (attempt + 1))
        return False

    def flush(self) -> None:
        """Record every concluded run whose end is still only in memory (disk freed)."""
        with self._lock:
            pending = list(self._unrecorded)
        for run_id in pending:
            if self.active_run != run_id:
                self._record(run_id, attempts=1)

    def unrecorded(self, run_id: int) -> tuple[str, str] | None:
        """A run's state and message while its end is held in memory only."""
        with self._lock:
            end = self._unrecorded.get(run_id)
        if end is None or self.active_run == run_id:
            return None
        target, reason, actor = end
        return target.value, f"{reason} ({actor})"

    def _finish(
        self, session: Session, run: Run, target: RunState, reason: str, actor: str
    ) -> None:
        for patch in run.patches:
            if patch.step not in (PatchStep.PENDING.value, PatchStep.STORED.value):
                self._patch_machine(session, run, patch).go(
                    PatchStep.PENDING, reason="not stored: it will be scanned again"
                )
        if RunState(run.state) != target:
            self._transition(session, run, target, reason, actor)
        if target in (RunState.FAILED, RunState.FAULT):
            self.events.emit("fault", reason, run_id=run.id, data={"state": target.value})
