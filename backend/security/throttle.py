"""Failed logins, throttled: after ``attempts`` failures of a name or of an address within
``window`` seconds, each further try waits twice as long as the last (up to ``longest``)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class Throttle:
    def __init__(
        self,
        attempts: int,
        *,
        window: float = 900.0,
        first: float = 30.0,
        longest: float = 900.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.attempts = attempts
        self.window = window
        self.first = first
        self.longest = longest
        self.clock = clock
        self._failures: dict[str, list[float]] = {}
        self._lock = threading.Lock()

    def wait(self, *keys: str) -> float:
        """Seconds before any of ``keys`` may try again (0: now)."""
        now = self.clock()
        longest = 0.0
        with self._lock:
            for key in keys:
                times = [t for t in self._failures.get(key, []) if now - t < self.window]
                if not times:  # nothing recent: forgotten (names tried once do not pile up)
                    self._failures.pop(key, None)
                    continue
                self._failures[key] = times
                extra = len(times) - self.attempts
                if extra >= 0:
                    pause = min(self.first * 2.0**extra, self.longest)
                    longest = max(longest, times[-1] + pause - now)
        return max(longest, 0.0)

    def failed(self, *keys: str) -> None:
        now = self.clock()
        with self._lock:
            if len(self._failures) > 100_000:  # a flood of names: keep only the recent ones
                self._failures = {
                    k: v for k, v in self._failures.items() if now - v[-1] < self.window
                }
            for key in keys:
                self._failures.setdefault(key, []).append(now)

    def succeeded(self, *keys: str) -> None:
        with self._lock:
            for key in keys:
                self._failures.pop(key, None)
