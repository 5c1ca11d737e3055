"""Simulated time: scaled wall time, or as fast as possible (time advances only on demand)."""

from __future__ import annotations

import threading
import time


class SimClock:
    """A clock of simulated seconds.

    Parameters
    ----------
    speed : float or None
        Simulated seconds per wall second; ``None`` runs as fast as possible: time stands still
        until :meth:`advance` or :meth:`advance_to` moves it (a simulator then jumps over waits).
    """

    def __init__(self, speed: float | None = None) -> None:
        if speed is not None and not speed > 0:
            raise ValueError(f"speed must be positive or None (as fast as possible), got {speed}")
        self.speed = speed
        self._lock = threading.Lock()
        self._offset = 0.0
        self._wall0 = time.monotonic()

    @property
    def fast(self) -> bool:
        """True when time runs as fast as possible."""
        return self.speed is None

    def now(self) -> float:
        with self._lock:
            if self.speed is None:
                return self._offset
            return self._offset + self.speed * (time.monotonic() - self._wall0)

    def advance(self, seconds: float) -> float:
        """Move simulated time forward by ``seconds`` (on a scaled clock: wait for it)."""
        if seconds < 0:
            raise ValueError("time only moves forward")
        if self.speed is None:
            with self._lock:
                self._offset += seconds
                return self._offset
        time.sleep(seconds / self.speed)
        return self.now()

    def advance_to(self, t: float) -> float:
        """Move simulated time forward to ``t`` (no-op if it is already later)."""
        return self.advance(max(0.0, t - self.now()))
