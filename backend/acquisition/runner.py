"""The acquisition runner: one worker thread drives the instrument through a run's patches.

The state machine (:mod:`backend.acquisition.state`) decides what may happen; this module
makes it happen on the hardware. Every transition is committed to the database and published
as an event before the next step starts. The HTTP handlers only ask (start, pause, resume,
abort, reset); the worker thread alone touches the instrument while a run is active.

* Pause takes effect at the next step boundary where the tip is off the surface (before a
  patch's ``move`` or ``land``): a pause asked for during landing or scanning waits for that
  patch to be stored.
* Abort is checked between steps and before every scan line; then the safe state.
* Any fault: the safe state, the run ``failed`` with a message for the operator, the patch
  back to ``pending``. If the safe state cannot be confirmed the run goes to ``fault``, which
  blocks the instrument until an operator resets it.

Its parts: the patch loop (:mod:`backend.acquisition.patch_loop`), how a run ends
(:mod:`backend.acquisition.ending`), and what keeps the instrument safe with no run driving it,
recovery after a restart and the supervisor between runs (:mod:`backend.acquisition.unattended`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from backend.acquisition.control import Abort, Conflict, Control, NotFound, describe
from backend.acquisition.ending import RunEnding
from backend.acquisition.patch_loop import PatchLoop
from backend.acquisition.rescans import Rescans, Verdict
from backend.acquisition.state import (
    STARTABLE,
    PatchStep,
    RunState,
)
from backend.acquisition.status import read_instrument
from backend.acquisition.unattended import UnattendedSafety
from backend.db.models import Run
from backend.db.space import StorageFull, check_space, full_message, is_full
from backend.events import EventBus
from backend.live_merge import LiveMergeService
from hardware.errors import CrashError, Interrupted, SafeStateError
from hardware.microscope import Microscope
from hardware.procedures import safe_state

log = logging.getLogger("mosaic_afm.runner")

#: What a run in fault after a crash asks of the operator.
TIP_CHECK = (
    "The tip may be damaged: nothing lands until an operator inspects or changes it and "
    "resets the run with a note"
)


class Runner(RunEnding, PatchLoop, UnattendedSafety):
    """Runs acquisitions on one instrument, one run at a time.

    Parameters
    ----------
    microscope : Microscope
    sessions : sessionmaker
    events : EventBus
    on_completed : callable(run_id), optional
        Called (from the worker thread) when a run completes, e.g. to start its merge.
    data_dir : Path
        Where patches are stored: its free space is checked before a run and every patch.
    reserve : int
        Bytes to keep free there beyond what a patch needs.
    """

    def __init__(
        self,
        microscope: Microscope,
        sessions: sessionmaker[Session],
        events: EventBus,
        *,
        on_completed: Callable[[int], None] | None = None,
        data_dir: Path = Path("."),
        reserve: int = 0,
    ) -> None:
        self.microscope = microscope
        self.sessions = sessions
        self.events = events
        self.on_completed = on_completed
        self._lock = threading.RLock()
        self._thread: threading.Thread | None = None
        self._control: Control | None = None
        self._io = threading.Lock()  # one user of the instrument links at a time
        self._busy: str | None = None  # what holds the instrument outside a run
        self._snapshot: dict[str, Any] = {}
        #: runs concluded whose end the database did not take yet: (state, reason, actor)
        self._unrecorded: dict[int, tuple[RunState, str, str]] = {}
        self.data_dir = data_dir
        self.reserve = reserve
        #: room one patch needs on disk, bytes (set per run from its pixels)
        self.patch_bytes = 0
        self._supervisor: threading.Thread | None = None
        self._stopping = threading.Event()
        #: the gate's verdicts to act on, and the faults armed for simulated patches
        self.rescans = Rescans(events)
        #: where stored patches are merged live and judged (None: nowhere)
        self.live: LiveMergeService | None = None

    def tell_verdict(self, run_id: int, index: int, passed: bool, reason: str) -> None:
        """The live merge's word on a patch (any thread): acted on at the next patch."""
        self.rescans.tell(Verdict(run_id, index, passed, reason))

    def request_rescan(self, run_id: int, index: int, *, actor: str) -> None:
        """The operator marks a stored patch of the active run for re-scan."""
        self._active_control(run_id, "re-scan a patch of")
        with self.sessions() as session:
            run = self._get(session, run_id)
            patch = next((p for p in run.patches if p.index == index), None)
            if patch is None:
                raise NotFound(f"run {run_id} has no patch {index}")
            if patch.step != PatchStep.STORED.value:
                raise Conflict(f"patch {index} of run {run_id} is {patch.step}, not stored")
        self.rescans.tell(Verdict(run_id, index, False, "marked for re-scan", operator=actor))

    # -- what the API asks ------------------------------------------------------------------

    @property
    def active_run(self) -> int | None:
        with self._lock:
            alive = self._thread is not None and self._thread.is_alive()
            return self._control.run_id if alive and self._control else None

    def pending_request(self, run_id: int) -> str | None:
        with self._lock:
            control = self._control
        if control is None or control.run_id != run_id or self.active_run != run_id:
            return None
        return control.request()

    def start(self, run_id: int, *, actor: str) -> None:
        """Start (or resume from its first patch not stored) a planned, failed or
        interrupted run; :class:`StorageFull` when the data directory has no room. A run
        that has ended (the instrument safe) while its worker still records it is waited
        for (up to 5 s), not refused: a script that starts the next run on hearing that the
        last one ended must not be told the instrument is busy."""
        self._await_concluded(5.0)
        self.flush()
        with self._lock:
            if self._unrecorded:
                held = next(iter(self._unrecorded))
                raise StorageFull(
                    errno.ENOSPC,
                    f"run {held}'s end is not recorded yet: " + self._full_message(),
                )
        with self._lock:
            if self._busy is not None:
                raise Conflict(f"the instrument is busy ({self._busy}): start the run after it")
            busy = self._thread is not None and self._thread.is_alive()
            if busy and self._control is not None:
                raise Conflict(
                    f"run {self._control.run_id} is using the instrument: pause or abort it "
                    "first (one active run per instrument)"
                )
            with self.sessions() as session:
                run = self._get(session, run_id)
                blocked = session.scalars(
                    select(Run.id).where(Run.state == RunState.FAULT.value)
                ).first()
                if blocked is not None:
                    raise Conflict(
                        f"run {blocked} is in fault (safe state not confirmed): check the "
                        f"instrument and reset run {blocked} first"
                    )
                if RunState(run.state) not in STARTABLE | {RunState.COMPLETED, RunState.ABORTED}:
                    raise Conflict(
                        f"run {run_id} is {run.state}: only a planned, failed or interrupted "
                        "run can start"
                    )
                # completed and aborted runs are final: the table refuses them (HTTP 409)
                self.patch_bytes = _patch_bytes(run)
                check_space(self.data_dir, need=self.patch_bytes, reserve=self.reserve)
                self._transition(session, run, RunState.RUNNING, "started", actor)
            control = Control(run_id)
            self._control = control
            self._thread = threading.Thread(
                target=self._work, args=(control,), name=f"run-{run_id}", daemon=True
            )
            self._thread.start()

    def pause(self, run_id: int, *, actor: str) -> None:
        control = self._active_control(run_id, "pause")
        with control.wake:
            if control.abort:
                raise Conflict(f"run {run_id} is being aborted")
            control.pause, control.actor = True, actor
        self.events.emit(
            "request",
            f"run {run_id}: pause asked by {actor}; it takes effect once the tip is off the "
            "surface",
            run_id=run_id,
            data={"request": "pause", "actor": actor},
        )

    def resume(self, run_id: int, *, actor: str, wait: float = 5.0) -> None:
        """Resume a paused run, or restart a failed or interrupted one. A run that has ended
        (failed) while its thread still closes it (its file, the live merge) is waited for, up
        to ``wait`` s: asked for at once, its restart was refused as "running, not paused"."""
        if self.active_run == run_id and self._ended(run_id):
            with self._lock:
                thread = self._thread
            if thread is not None:
                thread.join(wait)
        if self.active_run != run_id:
            self.start(run_id, actor=actor)
            return
        control = self._active_control(run_id, "resume")
        with control.wake:
            if not control.pause:
                raise Conflict(f"run {run_id} is running, not paused")
            control.pause, control.actor = False, actor
            control.wake.notify_all()
        self._wait_for(run_id, lambda s: s != RunState.PAUSED, wait)

    def abort(self, run_id: int, *, actor: str, reason: str, wait: float = 30.0) -> None:
        """Abort a run; an active one ends in the safe state (waits up to ``wait`` s)."""
        if self.active_run == run_id:
            control = self._active_control(run_id, "abort")
            with control.wake:
                control.abort, control.actor, control.reason = True, actor, reason
                control.wake.notify_all()
            with self._lock:
                thread = self._thread
            if thread is not None:
                thread.join(wait)
            return
        with self._lock, self.sessions() as session:
            run = self._get(session, run_id)
            if self.active_run == run_id:  # started meanwhile
                raise Conflict(f"run {run_id} has just started: abort it again")
            self._transition(session, run, RunState.ABORTED, reason or "aborted", actor)

    def reset(self, run_id: int, *, actor: str, note: str, tip_changed: bool = False) -> None:
        """Leave ``fault`` after an operator's check, told in ``note`` (what they looked at:
        the tip inspected, or changed): confirm the safe state, then ``failed``. A changed
        tip on the simulated instrument is a new, whole tip."""
        with self._lock, self.sessions() as session:
            run = self._get(session, run_id)
            if RunState(run.state) != RunState.FAULT:
                raise Conflict(f"run {run_id} is {run.state}, not in fault: nothing to reset")
            try:
                self._safe_state()
            except SafeStateError as exc:
                raise Conflict(f"run {run_id} stays in fault: {exc}") from None
            if tip_changed and self.microscope.sim is not None:
                self.microscope.sim.change_tip()
            tip = "tip changed" if tip_changed else "tip not changed"
            self._transition(
                session,
                run,
                RunState.FAILED,
                f"reset by the operator ({tip}): {note}; safe state confirmed",
                actor,
            )

    @contextlib.contextmanager
    def exclusive(self, what: str) -> Iterator[None]:
        """The instrument for ``what`` (an SEM calibration moving the stage) while no run uses
        it: a run in progress or in fault, or another such use, is a :class:`Conflict`; a run
        asked to start meanwhile is refused. The tip is withdrawn first."""
        with self._lock:
            if self.active_run is not None:
                raise Conflict(f"run {self.active_run} is using the instrument: {what} waits")
            if self._busy is not None:
                raise Conflict(f"the instrument is busy ({self._busy}): {what} waits")
            with self.sessions() as session:
                fault = session.scalars(
                    select(Run.id).where(Run.state == RunState.FAULT.value)
                ).first()
            if fault is not None:
                raise Conflict(f"run {fault} is in fault: reset it before {what}")
            self._busy = what
        try:
            with self._io:
                self._safe_state()
                yield
        finally:
            with self._lock:
                self._busy = None

    def wait_idle(self, timeout: float) -> bool:
        with self._lock:
            thread = self._thread
        if thread is not None:
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def close(self, timeout: float = 30.0) -> None:
        """Server shutdown: stop an active run in the safe state (it stays resumable)."""
        self._stopping.set()
        with self._lock:
            control, thread = self._control, self._thread
        if control is not None and thread is not None and thread.is_alive():
            with control.wake:
                control.abort, control.shutdown, control.actor = True, True, "server"
                control.reason = "the server stopped during the run; resume to continue"
                control.wake.notify_all()
            thread.join(timeout)

    # -- instrument status ------------------------------------------------------------------

    def _await_concluded(self, timeout: float) -> None:
        """Wait up to ``timeout`` s for a worker that has concluded its run to end."""
        with self._lock:
            control, thread = self._control, self._thread
        if (
            control is not None
            and control.concluded
            and thread is not None
            and thread is not threading.current_thread()
        ):
            thread.join(timeout=timeout)

    def instrument_status(self) -> dict[str, Any]:
        """What the instrument is doing: live when idle, the worker's last reading when busy.
        A worker that has concluded its run (made safe, or retracted after its last patch:
        nothing more lands) but still records and announces the end, or starts the run's
        merge, no longer drives the instrument: it is reported idle, with the tip as the
        worker left it. A page that reads the instrument on hearing that a run completed must
        not find it still driven, however long the bookkeeping takes on loaded cores."""
        with self._lock:
            control = self._control
        active = self.active_run
        if active is not None and control is not None and control.concluded:
            return {
                "active_run": None,
                **self._snapshot,
                "safe_state": not self.tip_down,
                "loop_engaged": self.tip_down,
            }
        if active is None and self._io.acquire(timeout=0.2):
            try:
                self._snapshot = read_instrument(self.microscope)
            except Exception as exc:  # a broken link is a status, not a server error
                self._snapshot = {"error": describe(exc)}
            finally:
                self._io.release()
        if active is not None:  # the worker drives it: never "safe" while a run may land
            return {
                "active_run": active,
                **self._snapshot,
                "safe_state": False,
                "loop_engaged": self.tip_down,
            }
        return {"active_run": active, **self._snapshot}

    # -- the worker -------------------------------------------------------------------------

    def _work(self, control: Control) -> None:
        """The worker: scan, then conclude. Whatever fails, and however (the disk, the
        database, a bug), the instrument is made safe before anything is recorded, and the
        worker never ends without a conclusion."""
        try:
            with self._io:
                target, reason, actor, safe = self._attempt(control)
                self._conclude(control.run_id, target, reason, actor, safe=safe, control=control)
        except BaseException as exc:  # the last line of defence: no tip left down
            log.exception("run %s: the worker failed", control.run_id)
            self._conclude(
                control.run_id,
                RunState.FAULT,
                f"the acquisition worker failed ({describe(exc)}): check the instrument",
                "instrument",
                safe=True,
            )

    def _attempt(self, control: Control) -> tuple[RunState, str, str, bool]:
        """Scan the run's patches; return how it ended: (state, reason, actor, make safe)."""
        try:
            with self.sessions() as session:
                run = session.get(Run, control.run_id)
                if run is None:  # deleted under us: nothing to do
                    return RunState.FAILED, "the run was deleted", "system", True
                self._run_patches(session, run, control)
        except (Abort, Interrupted):
            target = RunState.INTERRUPTED if control.shutdown else RunState.ABORTED
            return target, control.reason or "aborted", control.actor, True
        except CrashError as exc:  # the tip may be damaged: no landing until someone looks
            log.error("run %s: %s", control.run_id, exc)
            return RunState.FAULT, f"{exc}. {TIP_CHECK}", "instrument", True
        except Exception as exc:
            log.exception("run %s: step failed", control.run_id)
            if is_full(exc):
                return RunState.FAILED, self._full_message(), "storage", True
            return RunState.FAILED, describe(exc), "instrument", True
        return RunState.COMPLETED, "every patch stored", "system", False

    def _try_safe_state(self) -> str | None:
        """The safe state; None when confirmed, else what went wrong (never raises)."""
        try:
            self._safe_state()
        except SafeStateError as exc:
            return str(exc)
        except Exception as exc:
            return f"safe state not confirmed ({describe(exc)})"
        return None

    def _full_message(self) -> str:
        return full_message(self.data_dir, need=self.patch_bytes, reserve=self.reserve)

    def _safe_state(self) -> None:
        m = self.microscope
        safe_state(
            m.loop, m.robot_z, (m.stage_x, m.stage_y, m.robot_x, m.robot_y), scanner=m.scanner
        )
        self.tip_down = False
        self._snapshot = {**self._snapshot, "safe_state": True, "loop_engaged": False}

    # -- helpers ----------------------------------------------------------------------------

    def _ended(self, run_id: int) -> bool:
        """Whether the run's recorded state is one it can start from (it has ended)."""
        with self.sessions() as session:
            return RunState(self._get(session, run_id).state) in STARTABLE

    def _get(self, session: Session, run_id: int) -> Run:
        run = session.get(Run, run_id)
        if run is None:
            raise NotFound(f"no run {run_id}")
        return run

    def _active_control(self, run_id: int, what: str) -> Control:
        with self._lock:
            control = self._control
            alive = self._thread is not None and self._thread.is_alive()
        if control is None or not alive or control.run_id != run_id:
            with self.sessions() as session:
                run = self._get(session, run_id)
                raise Conflict(f"cannot {what} run {run_id}: it is {run.state}, not running")
        return control

    def _wait_for(self, run_id: int, done: Callable[[RunState], bool], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.sessions() as session:
                run = self._get(session, run_id)
                if done(RunState(run.state)):
                    return
            time.sleep(0.01)


def _patch_bytes(run: Run) -> int:
    """Room one patch of ``run`` takes in its file, with HDF5's overhead, bytes."""
    return 8 * run.pixels_x * run.pixels_y * 2 + 64 * 1024
