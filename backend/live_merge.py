"""The live merge of a scanning run: every stored patch merged and judged while the run goes on.

The runner hands each stored patch over (:meth:`LiveMergeService.submit`) and goes on
scanning; a worker process (``spawn``, niced like the merge jobs' worker) holds the run's
:class:`merge.live.LiveMerge` and :class:`merge.live.Gate`, adds the patch, judges it, draws
the live mosaic and sends all back. A relay thread then keeps the newest mosaic for the API,
publishes an event per verdict and per update (``live``), and tells the runner which patches
failed (``on_verdict``). While no patch waits, the worker polishes the mosaic with a full
refinement, and stops it the moment one comes.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from backend.allocator import share_one_heap
from backend.events import EventBus
from backend.merge_worker import WORKER_NICENESS, PatchInput, die_with_parent, patch_id
from merge.live.gate import ScanRecord

log = logging.getLogger("mosaic_afm.live_merge")

#: Called (from the relay thread) with (run id, patch index, passed, reason).
OnVerdict = Callable[[int, int, bool, str], None]
#: Seconds the worker waits for a patch before it polishes the mosaic.
IDLE = 0.05


@dataclass
class LiveState:
    """What the service knows of one run's live merge."""

    heights: NDArray[np.float64] | None = None
    document: dict[str, Any] | None = None
    submitted: int = 0
    judged: int = 0
    #: per patch index, when it was handed over (monotonic seconds), until its update came back
    pending: dict[int, float] = field(default_factory=dict)
    #: seconds from a patch handed over to the live mosaic holding it, in order
    latencies: list[float] = field(default_factory=list)
    failed: str | None = None
    #: final looks asked for and answered (:meth:`LiveMergeService.final`)
    finals_asked: int = 0
    finals_done: int = 0


def _index(pid: str) -> int:
    return int(pid[1:])


def _live_child(inbox: Any, outbox: Any, parent: int | None = None) -> None:
    """Worker process: add, judge, draw; polish while idle; until told to stop."""
    if parent is not None:
        die_with_parent(parent)
    if hasattr(os, "nice"):
        os.nice(WORKER_NICENESS)
    share_one_heap()  # before the merge's threads start
    from merge.core.noise import estimate_noise
    from merge.live import Gate, LiveMerge

    live, gate = LiveMerge(), Gate()
    while True:
        try:
            message = inbox.get(timeout=IDLE)
        except queue.Empty:
            if live.full_due and live.polish(cancel=lambda: not inbox.empty()):
                outbox.put(("mosaic", None, *_snapshot(live)))
            continue
        kind = message[0]
        if kind == "stop":
            return
        try:
            if kind == "final":
                looks = gate.final(live.misfits())
                said = {_index(pid): (False, v.reason) for pid, v in looks.items() if not v.ok}
                for index in said:
                    live.remove(patch_id(index))
                    gate.forget(patch_id(index))
                outbox.put(("final", said))
                if said and len(live):
                    outbox.put(("mosaic", None, *_snapshot(live)))
                continue
            if kind == "remove":
                pid = patch_id(message[1])
                if pid in live.ids:
                    live.remove(pid)
                    gate.forget(pid)
                    if len(live):
                        outbox.put(("mosaic", None, *_snapshot(live)))
                continue
            _, p, record = message
            patch = p.to_patch()
            update = live.add(patch)
            verdicts = gate.judge(
                update,
                noise=float(estimate_noise(patch.heights)),
                record=record,
            )
            for pid, verdict in verdicts.items():
                if not verdict.ok:
                    live.remove(pid)
                    gate.forget(pid)
            judged = {_index(pid): (v.ok, v.reason) for pid, v in verdicts.items()}
            outbox.put(("judged", p.order, judged, update.seconds))
            if len(live):
                outbox.put(("mosaic", p.order, *_snapshot(live)))
        except Exception as exc:  # reported; the run goes on without a live mosaic
            outbox.put(("error", f"{type(exc).__name__}: {exc}"))


def _snapshot(live: Any) -> tuple[NDArray[np.float64], dict[str, Any]]:
    """The live mosaic and its document: the result contract of docs/design.md (origin, pixel size,
    shape, every patch's transform) plus ``patches_merged``."""
    mosaic = live.mosaic()
    patches = []
    for p, tr in zip(live.patches, live.transforms, strict=True):
        patches.append(
            {
                "id": p.id,
                "index": _index(p.id),
                "transform": {
                    "model": "rigid+zplane",
                    "rotation": tr.R.tolist(),
                    "translation": tr.t.tolist(),
                    "z_slope": tr.slope.tolist(),
                    "centre": tr.centre.tolist(),
                },
            }
        )
    document = {
        "format": "mosaic-afm/mosaic@1",
        "units": "m",
        "origin": [float(mosaic.origin[0]), float(mosaic.origin[1])],
        "pixel_size": [float(mosaic.pixel_size[0]), float(mosaic.pixel_size[1])],
        "shape": [int(mosaic.heights.shape[0]), int(mosaic.heights.shape[1])],
        "method": "default",
        "live": True,
        "patches_merged": len(live),
        "patches": patches,
    }
    return mosaic.heights, document


class LiveMergeService:
    """One live merge per scanning run, each in its worker process.

    Parameters
    ----------
    events : EventBus
    on_verdict : callable(run_id, index, passed, reason), optional
        Told of every verdict (from the relay thread): the runner re-scans what fails.
    """

    def __init__(self, events: EventBus, *, on_verdict: OnVerdict | None = None) -> None:
        self.events = events
        self.on_verdict = on_verdict
        self._ctx = mp.get_context("spawn")
        self._lock = threading.Lock()
        self._runs: dict[int, LiveState] = {}
        self._workers: dict[int, tuple[Any, Any, Any, threading.Thread]] = {}

    # -- the runner's side --------------------------------------------------------------------

    def submit(self, run_id: int, patch: PatchInput, record: ScanRecord) -> None:
        """Hand a stored patch (``patch.order`` is its index) to the run's live merge; never
        waits for it."""
        inbox = self._worker(run_id)[0]
        with self._lock:
            state = self._runs[run_id]
            state.submitted += 1
            state.pending[patch.order] = time.monotonic()
        inbox.put(("add", patch, record))

    def remove(self, run_id: int, index: int) -> None:
        """Take patch ``index`` out of the run's live mosaic (it is to be scanned again)."""
        with self._lock:
            worker = self._workers.get(run_id)
        if worker is not None:
            worker[0].put(("remove", index))

    def drain(self, run_id: int, timeout: float) -> bool:
        """Wait until every patch handed over was judged (or ``timeout`` seconds pass)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                state = self._runs.get(run_id)
                if state is None or state.failed or state.judged >= state.submitted:
                    return True
            time.sleep(0.02)
        return False

    def final(self, run_id: int, timeout: float) -> bool:
        """Ask for the gate's last look at every patch of the run (each neighbour there now);
        its verdicts come as the others do. Whether it answered within ``timeout`` s."""
        with self._lock:
            worker = self._workers.get(run_id)
            state = self._runs.get(run_id)
            if worker is None or state is None:
                return True
            state.finals_asked += 1
            asked = state.finals_asked
        worker[0].put(("final",))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if state.failed or state.finals_done >= asked:
                    return True
            time.sleep(0.02)
        return False

    def stop(self, run_id: int) -> None:
        """Stop the run's worker (its live mosaic stays readable)."""
        with self._lock:
            worker = self._workers.pop(run_id, None)
        if worker is None:
            return
        inbox, _, process, relay = worker
        inbox.put(("stop",))
        process.join(5)
        if process.is_alive():
            process.terminate()
            process.join(5)
        relay.join(5)

    def forget(self, run_id: int) -> None:
        """Drop what is held of a stopped run (its last mosaic kept elsewhere)."""
        with self._lock:
            if run_id not in self._workers:
                self._runs.pop(run_id, None)

    def close(self) -> None:
        for run_id in list(self._workers):
            self.stop(run_id)

    # -- the API's side -----------------------------------------------------------------------

    def mosaic(self, run_id: int) -> tuple[NDArray[np.float64], dict[str, Any]] | None:
        """The newest live mosaic of the run and its document (None before the first)."""
        with self._lock:
            state = self._runs.get(run_id)
            if state is None or state.heights is None or state.document is None:
                return None
            return state.heights, dict(state.document)

    def latencies(self, run_id: int) -> list[float]:
        """Seconds from each patch handed over to the live mosaic holding it."""
        with self._lock:
            state = self._runs.get(run_id)
            return list(state.latencies) if state is not None else []

    # -- inside -------------------------------------------------------------------------------

    def _worker(self, run_id: int) -> tuple[Any, Any, Any, threading.Thread]:
        with self._lock:
            worker = self._workers.get(run_id)
            if worker is not None:
                return worker
            self._runs.setdefault(run_id, LiveState())
            inbox, outbox = self._ctx.Queue(), self._ctx.Queue()
            process = self._ctx.Process(
                target=_live_child, args=(inbox, outbox, os.getpid()), daemon=True
            )
            process.start()
            relay = threading.Thread(
                target=self._relay, args=(run_id, outbox, process), name=f"live-{run_id}"
            )
            relay.daemon = True
            relay.start()
            worker = (inbox, outbox, process, relay)
            self._workers[run_id] = worker
            return worker

    def _relay(self, run_id: int, outbox: Any, process: Any) -> None:
        while True:
            try:
                message = outbox.get(timeout=0.5)
            except queue.Empty:
                if not process.is_alive():
                    with self._lock:
                        state = self._runs[run_id]
                        stopping = run_id not in self._workers
                        if not stopping and state.failed is None:
                            state.failed = "the live merge process ended unexpectedly"
                    return
                continue
            try:
                self._handle(run_id, message)
            except Exception:  # the relay never dies of one message
                log.exception("live merge of run %s: a message went wrong", run_id)

    def _handle(self, run_id: int, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "judged":
            _, index, said, seconds = message
            with self._lock:
                self._runs[run_id].judged += 1
            for judged, (ok, reason) in said.items():
                self.events.emit(
                    "live",
                    f"run {run_id}: patch {judged} "
                    + ("passes the quality gate" if ok else f"fails the quality gate: {reason}"),
                    run_id=run_id,
                    data={"patch": judged, "passed": ok, "reason": reason, "seconds": seconds},
                )
                if self.on_verdict is not None:
                    self.on_verdict(run_id, judged, ok, reason)
        elif kind == "mosaic":
            _, index, heights, document = message
            with self._lock:
                state = self._runs[run_id]
                state.heights, state.document = heights, document
                started = state.pending.pop(index, None) if index is not None else None
                if started is not None:
                    state.latencies.append(time.monotonic() - started)
            self.events.emit(
                "live",
                f"run {run_id}: live mosaic holds {document['patches_merged']} patches",
                run_id=run_id,
                data={"patches_merged": document["patches_merged"], "patch": index},
            )
        elif kind == "final":
            _, said = message
            for index, (ok, reason) in said.items():
                self.events.emit(
                    "live",
                    f"run {run_id}: patch {index} fails the quality gate's last look: {reason}",
                    run_id=run_id,
                    data={"patch": index, "passed": ok, "reason": reason, "final": True},
                )
                if self.on_verdict is not None:
                    self.on_verdict(run_id, index, ok, reason)
            with self._lock:
                self._runs[run_id].finals_done += 1
        elif kind == "error":
            with self._lock:
                self._runs[run_id].failed = str(message[1])
            log.warning("live merge of run %s: %s", run_id, message[1])
            self.events.emit(
                "live",
                f"run {run_id}: the live merge stopped ({message[1]}); the run goes on",
                run_id=run_id,
                data={"error": str(message[1])},
            )


def scan_record(heights: NDArray[np.float64], *, saturated: int, mistracked: int) -> ScanRecord:
    """What a patch's scan recorded of itself, for the quality gate: its lines, those without
    a single height (data the controller lost), and the counts the scanner kept of lines with
    Z saturated and with the loop mistracking."""
    lost = int((~np.isfinite(heights)).all(axis=1).sum())
    lines = heights.shape[0]
    return ScanRecord(
        lines=lines, lost=lost, saturated=min(saturated, lines), mistracked=min(mistracked, lines)
    )
