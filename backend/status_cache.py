"""Status documents rendered once and served until an event says they changed.

Twenty clients polling a run's status while it scans would otherwise each load the run and
its patches from the database and serialise them, on the two cores the instrument and the
merge also need. Every change to a run is announced on the event bus with its run id
(transitions, stored patches, merges, requests, faults), so a rendered document stays valid
until such an event; a version number per run keeps a render that raced an event from being
kept. The instrument's status is kept for a tenth of a second at most.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Hashable
from typing import Any

#: Seconds an instrument status document is served before it is read again.
INSTRUMENT_MAX_AGE = 0.1


class StatusCache:
    """Rendered (JSON bytes) run and instrument status; an :class:`EventBus` listener."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._runs: dict[int, bytes] = {}
        self._versions: dict[int, int] = {}
        self._epoch = 0  # bumped by events of no run: every run document is redone
        self._instrument: tuple[float, bytes] | None = None
        #: bumped by every event: a render of the instrument begun before one is not kept
        #: (a run's end read as "tip engaged" just before it would outlive the retraction)
        self._instrument_version = 0
        #: renders under way, by what they render (touched by the event loop only)
        self._renders: dict[Hashable, asyncio.Future[bytes]] = {}

    async def render(self, key: Hashable, make: Callable[[], bytes]) -> bytes:
        """``make()`` in a worker thread, once for every request waiting on the same
        ``key`` (twenty clients missing at once render one document, not twenty)."""
        future = self._renders.get(key)
        if future is None:
            future = asyncio.ensure_future(asyncio.to_thread(make))
            self._renders[key] = future
            future.add_done_callback(lambda _: self._renders.pop(key, None))
        return await asyncio.shield(future)

    def __call__(self, event: dict[str, Any]) -> None:
        run_id = event.get("run_id")
        with self._lock:
            self._instrument = None
            self._instrument_version += 1
            if run_id is None:
                self._epoch += 1
                self._runs.clear()
            else:
                self._versions[run_id] = self._versions.get(run_id, 0) + 1
                self._runs.pop(run_id, None)

    def run(self, run_id: int) -> tuple[bytes | None, tuple[int, int]]:
        """The kept document of ``run_id`` (None) and the version a new render belongs to."""
        with self._lock:
            return self._runs.get(run_id), (self._epoch, self._versions.get(run_id, 0))

    def keep_run(self, run_id: int, version: tuple[int, int], body: bytes) -> None:
        """Keep ``body`` unless an event about the run came since ``version`` was read."""
        with self._lock:
            if version == (self._epoch, self._versions.get(run_id, 0)):
                self._runs[run_id] = body

    def instrument(self) -> tuple[bytes | None, int]:
        """The kept instrument document (None) and the version a new render belongs to."""
        with self._lock:
            kept = self._instrument
            if kept is not None and time.monotonic() - kept[0] < INSTRUMENT_MAX_AGE:
                return kept[1], self._instrument_version
            return None, self._instrument_version

    def keep_instrument(self, version: int, body: bytes) -> None:
        """Keep ``body`` unless an event came since ``version`` was read."""
        with self._lock:
            if version == self._instrument_version:
                self._instrument = (time.monotonic(), body)
