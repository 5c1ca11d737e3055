"""Merge jobs: a run's stored patches merged in a separate process, one job at a time.

The API thread only queues a job. A dispatcher thread reads the patches from the run's HDF5
file, hands them to a worker process (``spawn``: the server's threads are not forked), relays
its progress (iteration, residual) as events, and stores the result in the run's file before
the job row says ``done``. Cancelling sets an event the merge polls every iteration; a worker
that does not stop within a few seconds is terminated. The worker itself:
:mod:`backend.merge_worker`.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import os
import queue
import threading
from datetime import UTC, datetime
from multiprocessing.synchronize import Event as MpEvent
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from backend.db.models import MergeJob, Run
from backend.db.patch_store import read_patch, write_merge
from backend.db.space import full_message, is_full
from backend.events import EventBus
from backend.merge_worker import PID_FILE, PatchInput, merge_child, patch_id, reap_leftover

log = logging.getLogger("mosaic_afm.merge_jobs")

STATES = ("queued", "running", "done", "failed", "cancelled")
FINAL = frozenset({"done", "failed", "cancelled"})
#: Seconds a cancelled worker gets to stop on its own before it is terminated.
CANCEL_GRACE = 5.0


class JobError(RuntimeError):
    """A job request that cannot be done (HTTP 409/422 at the API); says why."""


def scanned_open_loop(attrs: dict[str, Any]) -> bool:
    """Whether the server scanned a stored patch without a position sensor placing its rows
    (a Nanonis scan generator on open-loop piezos: no Y readings, or some missing). Such
    patches carry the scanner's bend, which the merge's self-calibration takes out; uploaded
    scans say nothing of their scanner (no readings recorded) and are merged as they are."""
    if "row_readings" not in attrs:
        return False
    readings = np.asarray(attrs["row_readings"], dtype=np.float64)
    return readings.size == 0 or not bool(np.all(np.isfinite(readings)))


class MergeService:
    """Queue, run, cancel and store merge jobs."""

    def __init__(
        self, sessions: sessionmaker[Session], events: EventBus, *, data_dir: Path = Path(".")
    ) -> None:
        self.sessions = sessions
        self.events = events
        self.data_dir = data_dir
        #: jobs that failed while the database could not take it: (job id, message)
        self._unrecorded: list[tuple[int, str]] = []
        self._queue: queue.Queue[int | None] = queue.Queue()
        self._ctx = mp.get_context("spawn")
        self._cancel: dict[int, MpEvent] = {}
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._dispatch, name="merge-jobs", daemon=True)
        self._started = False

    def start(self) -> None:
        if not self._started:
            self._thread.start()
            self._started = True

    def recover(self) -> None:
        """After a restart: a worker left running is killed, a job that was running failed;
        queued jobs run again."""
        note = reap_leftover(self.data_dir)
        if note is not None:
            log.warning("start-up: %s", note)
        with self.sessions() as session:
            for job in session.scalars(select(MergeJob).where(MergeJob.state == "running")):
                job.state, job.message = "failed", "the server stopped during the merge"
                job.finished_at = datetime.now(UTC)
            session.commit()
            queued = session.scalars(
                select(MergeJob.id).where(MergeJob.state == "queued").order_by(MergeJob.id)
            ).all()
        for job_id in queued:
            self._queue.put(job_id)

    def submit(
        self,
        run_id: int,
        *,
        method: str,
        parameters: dict[str, Any],
        patches: list[int] | None,
        requested_by: str = "auto",
    ) -> int:
        """Queue a merge of the run's stored patches (``patches``: indices, or all), asked
        for by ``requested_by``."""
        with self.sessions() as session:
            run = session.get(Run, run_id)
            if run is None:
                raise LookupError(f"no run {run_id}")
            stored = {p.index for p in run.patches if p.step == "stored"}
            chosen = sorted(stored) if patches is None else sorted(set(patches))
            missing = [i for i in chosen if i not in stored]
            if missing:
                raise JobError(
                    f"patches {missing} of run {run_id} are not stored; stored: "
                    f"{sorted(stored) if len(stored) < 50 else f'{len(stored)} patches'}"
                )
            if len(chosen) < 2:
                raise JobError(
                    f"run {run_id} has {len(chosen)} stored patch(es) to merge; need at least 2"
                )
            job = MergeJob(
                run_id=run_id,
                state="queued",
                method=method,
                parameters=parameters,
                patch_ids=chosen,
                requested_by=requested_by[:64],
            )
            session.add(job)
            session.commit()
            job_id = job.id
        self.events.emit(
            "merge",
            f"merge {job_id} of run {run_id} queued ({method}, {len(chosen)} patches)",
            run_id=run_id,
            data={"job": job_id, "state": "queued", "progress": 0.0},
        )
        self._queue.put(job_id)
        return job_id

    def cancel(self, job_id: int) -> None:
        with self.sessions() as session:
            job = session.get(MergeJob, job_id)
            if job is None:
                raise LookupError(f"no merge job {job_id}")
            if job.state in FINAL:
                raise JobError(f"merge {job_id} is already {job.state}")
            if job.state == "queued":
                self._set(session, job, "cancelled", "cancelled before it started")
                return
        with self._lock:
            event = self._cancel.get(job_id)
        if event is not None:
            event.set()

    def close(self) -> None:
        with self._lock:
            for event in self._cancel.values():
                event.set()
        self._queue.put(None)
        if self._started:
            self._thread.join(CANCEL_GRACE + 5)

    # -- the dispatcher ---------------------------------------------------------------------

    def _dispatch(self) -> None:
        """Run queued jobs one by one; a job's failure, even one the database refuses to
        record, never stops the dispatcher (the record is written once it can be)."""
        while True:
            try:
                job_id = self._queue.get(timeout=1.0)
            except queue.Empty:
                self._record_failures()
                continue
            if job_id is None:
                return
            self._record_failures()
            try:
                self._run(job_id)
            except Exception as exc:
                log.exception("merge %s failed", job_id)
                message = (
                    full_message(self.data_dir, then="merge again")
                    if is_full(exc)
                    else f"merge failed: {exc}"
                )
                self._unrecorded.append((job_id, message))
                self._record_failures()

    def _record_failures(self) -> None:
        still = []
        for job_id, message in self._unrecorded:
            try:
                with self.sessions() as session:
                    job = session.get(MergeJob, job_id)
                    if job is not None and job.state not in FINAL:
                        self._set(session, job, "failed", message)
            except Exception:
                log.warning("merge %s: its failure is not recorded yet", job_id, exc_info=True)
                still.append((job_id, message))
        self._unrecorded = still

    def _run(self, job_id: int) -> None:
        with self.sessions() as session:
            job = session.get(MergeJob, job_id)
            if job is None or job.state != "queued":
                return
            run = session.get(Run, job.run_id)
            if run is None:
                return
            path = run.file
            records = {p.index: p for p in run.patches}
            inputs = []
            bent = True  # every patch scanned here by a scanner without a position sensor
            for index in job.patch_ids or []:
                stored = read_patch(path, index)
                bent &= scanned_open_loop(stored.attrs)
                rec = records[index]
                inputs.append(
                    PatchInput(
                        id=patch_id(index),
                        heights=stored.heights,
                        origin=stored.origin,
                        pixel_size=stored.pixel_size,
                        order=index,
                        row=rec.row,
                        col=rec.col,
                    )
                )
            options = {"method": job.method, **(job.parameters or {})}
            if "self_calibrate" not in options and job.method == "default":
                options["self_calibrate"] = bent
            if "pixel_size" in options and options["pixel_size"] is not None:
                options["pixel_size"] = tuple(options["pixel_size"])
            cancel = self._ctx.Event()
            with self._lock:
                self._cancel[job_id] = cancel
            self._set(session, job, "running", "merging")
            out: Any = self._ctx.Queue()
            worker = self._ctx.Process(
                target=merge_child,
                args=(inputs, options, out, cancel, os.getpid()),
                daemon=True,
            )
            worker.start()
            pid_file = self.data_dir / PID_FILE
            with contextlib.suppress(OSError):
                pid_file.write_text(f"{worker.pid}\n")
            try:
                self._follow(session, job, path, worker, out, cancel)
            finally:
                with self._lock:
                    self._cancel.pop(job_id, None)
                if worker.is_alive():
                    worker.terminate()
                worker.join(5)
                pid_file.unlink(missing_ok=True)

    def _follow(
        self,
        session: Session,
        job: MergeJob,
        path: Path,
        worker: Any,
        out: Any,
        cancel: MpEvent,
    ) -> None:
        cancelled_at: float | None = None
        while True:
            try:
                message = out.get(timeout=0.5)
            except queue.Empty:
                if cancel.is_set():
                    import time

                    now = time.monotonic()
                    cancelled_at = cancelled_at or now
                    if now - cancelled_at > CANCEL_GRACE:
                        worker.terminate()
                        self._set(session, job, "cancelled", "cancelled (worker terminated)")
                        return
                if not worker.is_alive() and out.empty():
                    self._set(session, job, "failed", "the merge process ended unexpectedly")
                    return
                continue
            kind = message[0]
            if kind == "status":
                _, stage, detail, fraction, eta = message
                job.progress = min(0.99, float(fraction))
                session.commit()
                when = f", {round(eta)} s to go" if eta is not None else ""
                self._running(
                    job,
                    f"{detail or stage}, {100 * job.progress:.0f} %{when}",
                    stage=stage,
                    detail=detail,
                    progress=job.progress,
                    eta_s=eta,
                )
            elif kind == "progress":
                _, iteration, residual = message
                job.iteration, job.residual = int(iteration), float(residual)
                session.commit()
                self._running(
                    job,
                    f"iteration {iteration}, residual {residual * 1e9:.3f} nm",
                    iteration=int(iteration),
                    residual=float(residual),
                    progress=job.progress,
                )
            elif kind == "done":
                _, heights, document = message
                job.result_group = write_merge(path, job.id, heights, document)
                job.progress = 1.0
                self._set(
                    session,
                    job,
                    "done",
                    f"merged: mosaic {heights.shape[1]} x {heights.shape[0]} px",
                )
                return
            elif kind == "cancelled":
                self._set(session, job, "cancelled", "cancelled")
                return
            else:
                self._set(session, job, "failed", str(message[1]))
                return

    def _running(self, job: MergeJob, said: str, **data: Any) -> None:
        """An event of a running job: ``said`` after its name, ``data`` beside its state."""
        self.events.emit(
            "merge",
            f"merge {job.id}: {said}",
            run_id=job.run_id,
            data={"job": job.id, "state": "running", **data},
        )

    def _set(self, session: Session, job: MergeJob, state: str, message: str) -> None:
        job.state, job.message = state, message
        if state in FINAL:
            job.finished_at = datetime.now(UTC)
        session.commit()
        self.events.emit(
            "merge",
            f"merge {job.id} of run {job.run_id}: {state} ({message})",
            run_id=job.run_id,
            data={"job": job.id, "state": state, "progress": job.progress, "message": message},
        )
