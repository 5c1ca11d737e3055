"""The simulated Nanonis scan generator: a frame rastered over the world, line by line.

The controller drives the scan piezos (the probe robot's X and Y channels in fine mode, with
their hysteresis and creep) itself, the way its high-voltage amplifiers would: every line is
a forward trace and a backward trace at the programmed times per line, both recorded through
the force loop's physics (:meth:`~hardware.sim.instrument.SimulatedAFM.record_line`). The frame
may be rotated (Nanonis: a positive angle turns it clockwise) and shifted from the middle of
the scan range. Heights come out as the Z piezo signal, ``Z = high limit - extension``.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hardware.errors import CrashError
from hardware.sim.instrument import SimulatedAFM
from hardware.smaract_mcs import MAX_LEVEL

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Frame:
    """A scan frame in the controller's XY (metres, 0 at the middle of the range)."""

    centre: tuple[float, float] = (0.0, 0.0)
    size: tuple[float, float] = (1e-6, 1e-6)
    angle: float = 0.0  # degrees, clockwise

    def to_xy(self, u: float, v: float) -> tuple[float, float]:
        """Controller XY of frame coordinates ``(u, v)`` (from the frame's centre)."""
        a = math.radians(self.angle)
        c, s = math.cos(a), math.sin(a)
        return self.centre[0] + u * c + v * s, self.centre[1] - u * s + v * c

    def inside(self, half_range: tuple[float, float]) -> bool:
        """Whether every corner lies within ± ``half_range``."""
        w, h = self.size
        for u in (-w / 2, w / 2):
            for v in (-h / 2, h / 2):
                x, y = self.to_xy(u, v)
                if abs(x) > half_range[0] * (1 + 1e-6) or abs(y) > half_range[1] * (1 + 1e-6):
                    return False
        return True


@dataclass
class FrameData:
    """What one frame recorded: Z forward and backward (rows in scan order, NaN not yet)."""

    forward: FloatArray
    backward: FloatArray
    up: bool


def ramp_xy(afm: SimulatedAFM, xy: tuple[float, float], *, duration: float | None) -> None:
    """Ramp the scan piezos to controller XY ``xy`` (metres) over ``duration`` s; None moves
    fast and waits until both arrive (a fly-over between lines)."""
    clock = afm.clock
    t = clock.now()
    axes = afm.robot_device.axes[:2]
    for axis, value in zip(axes, xy, strict=True):
        r = axis.params.fine_range
        level = float(np.clip((value + r / 2) / r * MAX_LEVEL, 0, MAX_LEVEL))
        delta = abs(level - axis.level_at(t))
        rate = MAX_LEVEL * 10.0 if duration is None else max(delta / duration, 1.0)
        axis.scan(round(level), max(1, round(rate)), t)
    if duration is None:
        clock.advance_to(max(axis.busy_until(t) for axis in axes))


class FrameScan:
    """Rasters ``frame`` at ``pixels`` = (nx, ny) over the world ``afm``.

    ``times`` = (forward, backward) seconds per line. :meth:`run` scans every line, each
    holding ``lock``, and stops before the next line once ``stop`` is set.
    """

    def __init__(
        self,
        afm: SimulatedAFM,
        frame: Frame,
        pixels: tuple[int, int],
        times: tuple[float, float],
        *,
        up: bool = True,
    ) -> None:
        self.afm, self.frame, self.pixels, self.times, self.up = afm, frame, pixels, times, up
        nx, ny = pixels
        self.data = FrameData(np.full((ny, nx), np.nan), np.full((ny, nx), np.nan), up)
        z = afm.robot_device.axes[2]
        self.z_high = 0.5 * z.params.fine_range

    def run(
        self,
        lock: AbstractContextManager[Any],
        stop: threading.Event,
        on_line: Callable[[int], None] | None = None,
    ) -> None:
        """Scan every line (``on_line(k)`` after line ``k``, under the lock)."""
        for k in range(self.pixels[1]):
            with lock:
                if stop.is_set():
                    return
                self._line(k)
                if on_line is not None:
                    on_line(k)

    def _line(self, k: int) -> None:
        ny = self.pixels[1]
        w, h = self.frame.size
        i = k if self.up else ny - 1 - k
        v = -h / 2 + (i + 0.5) * h / ny
        start, end = self.frame.to_xy(-w / 2, v), self.frame.to_xy(w / 2, v)
        self._move(start, speed=None)
        self.data.forward[k] = self._trace(start, end, self.times[0])
        self.data.backward[k] = self._trace(end, start, self.times[1])[::-1]

    # -- one trace ----------------------------------------------------------------------------

    def _move(self, xy: tuple[float, float], *, speed: float | None) -> None:
        ramp_xy(self.afm, xy, duration=speed)

    def _trace(
        self, start: tuple[float, float], end: tuple[float, float], duration: float
    ) -> FloatArray:
        """One trace from ``start`` to ``end`` in ``duration`` s: Z at each of nx pixels."""
        afm, nx = self.afm, self.pixels[0]
        z = afm.robot_device.axes[2]
        if afm.pll_lost or afm.crashed:  # no signal to regulate on: the tip is withdrawn
            afm.withdraw()
        if not afm.engaged():  # Z held (or withdrawn): the piezos still move, Z stands
            self._move(end, speed=duration)
            afm.clock.advance(duration)
            return np.full(nx, self.z_high - z.extension(afm.clock.now()))
        t = afm.clock.now()
        tip0 = afm.params.z_top - (z.true_position(t) - z.extension(t))
        self._move(end, speed=duration)
        try:
            heights, _ = afm.record_line(nx, duration)
        except CrashError:
            afm.withdraw()
            return np.full(nx, np.nan)
        afm.track()  # the loop runs on through the turn at the line's end
        out: FloatArray = heights - tip0 + self.z_high
        return out
