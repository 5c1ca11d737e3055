"""Simulated time: as fast as possible, or paced at a number of simulated seconds per wall second.

A real controller times its lines in hardware: the milliseconds its host takes between two
commands are not seen in the scan. A simulator that read its time off the wall clock, scaled,
would multiply the host's hiccups by the speed (at 50 x, 20 ms of a busy host become a second of
creep between two lines, and every patch bends differently). So simulated time moves on demand,
by the instrument's own actions (a line, a move, a wait for a move), and a paced clock takes
``seconds / speed`` of wall time for each. Only a silence longer than :data:`IDLE` wall seconds
(the host gone, an operator thinking) passes as time by itself: drift goes on and a watchdog
trips, as on a real instrument.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

#: A silence of more wall seconds than this between two looks at the clock passes as time.
IDLE = 1.0


class SimClock:
    """A clock of simulated seconds.

    Parameters
    ----------
    speed : float or None
        Simulated seconds per wall second; ``None`` runs as fast as possible: waits take no
        wall time, and time stands still between them whatever the silence.
    wall, sleep : callables, keyword-only
        The wall clock and its sleep (``time.monotonic`` and ``time.sleep``; tests pass their
        own).
    """

    def __init__(
        self,
        speed: float | None = None,
        *,
        wall: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if speed is not None and not speed > 0:
            raise ValueError(f"speed must be positive or None (as fast as possible), got {speed}")
        self.speed = speed
        self._wall, self._sleep = wall, sleep
        self._lock = threading.Lock()
        self._offset = 0.0
        self._seen = wall()  # wall time of the last look
        self._until = -math.inf  # simulated time the advances in flight run to

    @property
    def fast(self) -> bool:
        """True when time runs as fast as possible."""
        return self.speed is None

    def now(self) -> float:
        with self._lock:
            return self._sync()

    def advance(self, seconds: float) -> float:
        """Move simulated time forward by ``seconds`` (on a paced clock: wait for it)."""
        if seconds < 0:
            raise ValueError("time only moves forward")
        with self._lock:
            target = self._sync() + seconds
            if self.speed is None:
                self._offset = target
                return target
            self._until = max(self._until, target)
        self._sleep(seconds / self.speed)
        with self._lock:
            self._offset = max(self._sync(), target)
            return self._offset

    def advance_to(self, t: float) -> float:
        """Move simulated time forward to ``t`` (no-op if it is already later)."""
        return self.advance(max(0.0, t - self.now()))

    def _sync(self) -> float:
        """Simulated time now (under the lock): an advance in flight runs at the clock's speed
        towards its end; else a silence past :data:`IDLE` passes whole."""
        wall = self._wall()
        elapsed, self._seen = wall - self._seen, wall
        if self.speed is not None:
            if self._offset < self._until:
                self._offset = min(self._until, self._offset + self.speed * elapsed)
            elif elapsed > IDLE:
                self._offset += self.speed * elapsed
        return self._offset
