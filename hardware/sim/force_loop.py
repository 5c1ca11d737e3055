"""The simulated AFM's force loop over one scan line
(:class:`~hardware.sim.instrument.SimulatedAFM`).

The loop is the analogue Z loop of the AFM controller: it drives the robot's fine Z extension
from the frequency shift. On the repulsive branch the shift maps one to one onto distance, so
the loop is a distance regulator of finite bandwidth: a first-order system in continuous time,
``de/dt = 2π f (u - e)``, ``e`` the extension and ``u`` the extension that puts the tip at the
set-point. The surface under the tip is known at knots along its path (a few nanometres
apart); between knots ``u`` is linear in time and the loop's response is exact there (a
first-order hold), so what the loop does depends on time, speed and slope, never on how many
pixels a line has: a ramp of slope ``s`` crossed at speed ``v`` is followed ``s v / (2π f)``
behind. Where the loop leaves that regime (off the surface beyond the attractive minimum the
signal is weak and the loop approaches at its slew rate, "parachuting"; Z at an end of its
range; a crash) the line is integrated knot by knot instead. Pure functions of the surface
under the tip's path and the loop's settings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from hardware.errors import CrashError

FloatArray = NDArray[np.float64]

#: The rate at which the loop approaches a surface it has lost, metres per second: beyond
#: the attractive minimum the frequency shift hardly changes with distance.
SLEW_RATE = 40e-6
#: The approach rate of a loop that parachutes (a spoiled patch, :mod:`hardware.sim.faults`).
PARACHUTE_RATE = 0.8e-6


@dataclass(frozen=True)
class Loop:
    """The loop's settings over one line: its ``bandwidth`` (Hz), the time between knots
    (``knot_time``, s) and the knots per pixel (``substeps``), the fine Z range (metres), the
    distances (metres) where the attractive branch ends and where the tip crashes, and the
    rate (m/s) at which it approaches a surface it lost (:data:`SLEW_RATE`)."""

    bandwidth: float
    knot_time: float
    substeps: int
    zrange: float
    branch_end: float
    crash_depth: float
    slew_rate: float = SLEW_RATE

    @property
    def decay(self) -> float:
        """How much of an error is left after one knot's time."""
        return math.exp(-2 * math.pi * self.bandwidth * self.knot_time)

    @property
    def hold(self) -> tuple[float, float]:
        """The first-order hold's weights of the knot reached and the knot left."""
        e, wh = self.decay, 2 * math.pi * self.bandwidth * self.knot_time
        b0 = 1.0 - (1.0 - e) / wh
        return b0, (1.0 - e) - b0

    @property
    def slew(self) -> float:
        """The most the loop extends in one knot's time off the surface, metres."""
        return self.slew_rate * self.knot_time


@dataclass(frozen=True)
class LoopLine:
    """One line as the loop followed it: per pixel the tip's height (lab, metres; the mean over
    its knots), the extension at the line's end (metres), the error it held for a quarter of
    the line (metres, :func:`held_error`), and whether Z met an end of its range."""

    heights: FloatArray
    extension: float
    tracking: float
    saturated: bool


def follow_line(
    surface: FloatArray, tip0: float, extension: float, distance: float, loop: Loop
) -> LoopLine:
    """The loop over one line: ``surface`` (samples * substeps,) the surface's height (lab,
    metres) under the tip at every knot, ``tip0`` the tip's height with Z retracted,
    ``extension`` the fine Z extension at the start and ``distance`` the set-point's tip-sample
    distance (metres). The loop starts settled on the line's first knot (it followed the
    surface during the fly-back). Raises :class:`~hardware.errors.CrashError` when the tip
    crashes, naming the speed and slope that did it."""
    if len(surface) % loop.substeps:
        raise ValueError(
            f"{len(surface)} knots are not a whole number of pixels of {loop.substeps}"
        )
    samples = len(surface) // loop.substeps
    target = tip0 - surface - distance
    b0, b1 = loop.hold
    e = loop.decay
    # the state before the first knot: the extension held, the target of a settled loop
    zi = [b1 * target[0] + e * extension]
    exts = lfilter([b0, b1], [1.0, -e], target, zi=zi)[0]
    before = tip0 - np.concatenate([[extension], exts[:-1]]) - surface
    steps = np.diff(np.concatenate([[extension], exts]))
    linear = (
        not np.any((before > loop.branch_end) & (steps > loop.slew))
        and exts.min() > 0.0
        and exts.max() < loop.zrange
        and (tip0 - exts - surface).min() >= loop.crash_depth
    )
    if not linear:
        return _integrated(surface, tip0, extension, distance, loop, samples)
    heights = (tip0 - exts).reshape(samples, loop.substeps).mean(axis=1)
    tracking = held_error(tip0 - exts - surface - distance)
    return LoopLine(heights, float(exts[-1]), tracking, False)


def _integrated(
    surface: FloatArray, tip0: float, ext: float, distance: float, loop: Loop, samples: int
) -> LoopLine:
    """:func:`follow_line` knot by knot, with the slew limit, the range and the crash."""
    sub = loop.substeps
    b0, b1 = loop.hold
    e = loop.decay
    line = np.zeros(samples)
    lags = np.empty(samples * sub)
    saturated = False
    previous = tip0 - surface[0] - distance  # settled on the first knot
    for k in range(samples * sub):
        target = tip0 - surface[k] - distance
        step = e * ext + b0 * target + b1 * previous - ext
        if tip0 - ext - surface[k] > loop.branch_end:
            step = min(step, loop.slew)
        previous = target
        ext = min(max(ext + step, 0.0), loop.zrange)
        if ext in (0.0, loop.zrange):
            saturated = True
        if tip0 - ext - surface[k] < loop.crash_depth:
            raise CrashError(_crash_message(surface, k, loop, at_limit=ext == 0.0))
        line[k // sub] += (tip0 - ext) / sub
        lags[k] = tip0 - ext - surface[k] - distance  # what the loop's update left
    return LoopLine(line, ext, held_error(lags), saturated)


def _crash_message(surface: FloatArray, k: int, loop: Loop, *, at_limit: bool) -> str:
    """Why the tip crashed at knot ``k``: Z at its limit, or the surface rising faster than
    the loop follows (the rate it rose at, and what the loop's bandwidth allows)."""
    if at_limit:
        return (
            "the tip crashed into the surface: Z was fully retracted (the end of its fine "
            "range) and the surface came closer (drift, or a patch taller than Z's range)"
        )
    lo = max(k - loop.substeps, 0)
    rise = (surface[k] - surface[lo]) / max((k - lo) * loop.knot_time, loop.knot_time)
    return (
        f"the tip crashed into the surface: it rose at {rise * 1e6:.3g} µm/s under the tip, "
        f"more than the force loop's {loop.bandwidth:g} Hz follows (lower the line rate)"
    )


def held_error(lags: FloatArray) -> float:
    """The error a loop's updates ``lags`` (metres) stood at or above for a quarter of them."""
    return float(np.quantile(np.abs(lags), 0.75))
