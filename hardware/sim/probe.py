"""The self-sensing Akiyama probe in frequency modulation: Δf against tip-sample distance.

``Δf(d) = -A exp(-d / λa) + B exp(-d / λr)`` with the repulsive range ``λr`` shorter than the
attractive ``λa``: far away Δf is zero, approaching it dips (attraction) and then rises steeply
through zero into repulsion. The force loop works on the repulsive branch, where Δf falls
monotonically with distance; a set-point of +10 Hz sits about 2 nm above the surface. Driving
the tip into the surface sends Δf beyond the PLL's range: the lock is lost (a crash).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ProbeModel:
    """Interaction of an Akiyama probe (SI units: metres, hertz)."""

    attraction: float = 20.0
    attraction_length: float = 5e-9
    repulsion: float = 200.0
    repulsion_length: float = 1e-9
    noise: float = 0.1
    pll_range: float = 500.0
    amplitude: float = 10e-9

    def delta_f(self, distance: FloatArray | float) -> FloatArray:
        """Frequency shift (Hz) at tip-sample ``distance`` (m; negative inside the surface)."""
        d = np.asarray(distance, dtype=np.float64)
        out: FloatArray = -self.attraction * np.exp(-d / self.attraction_length) + (
            self.repulsion * np.exp(-d / self.repulsion_length)
        )
        return out

    def slope(self, distance: float) -> float:
        """dΔf/dd (Hz/m) at ``distance``."""
        return self.attraction / self.attraction_length * math.exp(
            -distance / self.attraction_length
        ) - self.repulsion / self.repulsion_length * math.exp(-distance / self.repulsion_length)

    def distance_at(self, setpoint: float) -> float:
        """The distance (m) on the repulsive branch where Δf equals ``setpoint`` (bisection)."""
        # the branch runs from deep inside (huge Δf) up to the attractive minimum
        lo, hi = -20 * self.repulsion_length, self._minimum()
        if not self._delta_f(hi) < setpoint < self._delta_f(lo):
            raise ValueError(f"set-point {setpoint} Hz is not on the repulsive branch")
        return self._descend_to(setpoint, lo, hi)

    def attraction_minimum(self) -> float:
        """Distance (m) of the attractive minimum: the end of the repulsive branch."""
        return self._minimum()

    def crash_distance(self) -> float:
        """Distance (m, negative) at which Δf leaves the PLL's range: a crash."""
        return self._descend_to(self.pll_range, -50 * self.repulsion_length, 0.0)

    def _delta_f(self, d: float) -> float:
        """:meth:`delta_f` of one distance, in scalar arithmetic (the solvers' hot path)."""
        return -self.attraction * math.exp(-d / self.attraction_length) + (
            self.repulsion * math.exp(-d / self.repulsion_length)
        )

    def _descend_to(self, value: float, lo: float, hi: float) -> float:
        """Where Δf, falling from ``lo`` to ``hi``, crosses ``value`` (80 bisections)."""
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if self._delta_f(mid) > value:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def _minimum(self) -> float:
        ra = self.attraction / self.attraction_length
        rr = self.repulsion / self.repulsion_length
        inv = 1 / self.repulsion_length - 1 / self.attraction_length
        return math.log(rr / ra) / inv

    def locked(self, delta_f: float) -> bool:
        """Whether the PLL still follows the resonance."""
        return abs(delta_f) < self.pll_range
