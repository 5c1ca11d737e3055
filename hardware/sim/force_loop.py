"""The simulated AFM's force loop over one scan line
(:class:`~hardware.sim.instrument.SimulatedAFM`).

The loop is the analogue Z loop of the AFM controller: it drives the robot's fine Z extension
from the frequency shift. On the repulsive branch the shift maps one to one onto distance, so
the loop is a distance regulator of finite bandwidth: a first-order filter of the extension
that puts the tip at the set-point, run over the whole line at once. Where it would leave that
regime (beyond the attractive minimum the signal is weak and the loop approaches at its slew
rate, "parachuting"; Z at an end of its range; a crash) the line is integrated update by update
instead. Pure functions of the surface under the tip's path and the loop's settings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from hardware.errors import CrashError

FloatArray = NDArray[np.float64]

#: Largest error the loop acts on off the surface, metres: its slew-rate limit (it approaches
#: by its gain times this per update).
MAX_LOOP_STEP = 20e-9
#: The slew-rate limit of a loop that parachutes (a spoiled patch, :mod:`hardware.sim.faults`).
PARACHUTE_STEP = 0.4e-9


@dataclass(frozen=True)
class Loop:
    """The loop's settings over one line: its ``gain`` per update (``1 - exp(-2π f dt)``),
    the updates per pixel (``substeps``), the fine Z range (metres), the distances (metres)
    where the attractive branch ends and where the tip crashes, and the largest error it acts
    on off the surface (metres, :data:`MAX_LOOP_STEP`)."""

    gain: float
    substeps: int
    zrange: float
    branch_end: float
    crash_depth: float
    max_step: float = MAX_LOOP_STEP


@dataclass(frozen=True)
class LoopLine:
    """One line as the loop followed it: per pixel the tip's height (lab, metres; the mean over
    its updates), the extension at the line's end (metres), the error it held for a quarter of
    the line (metres, :func:`held_error`), and whether Z met an end of its range."""

    heights: FloatArray
    extension: float
    tracking: float
    saturated: bool


def follow_line(
    surface: FloatArray, tip0: float, extension: float, distance: float, loop: Loop
) -> LoopLine:
    """The loop over one line: ``surface`` (samples * substeps,) the surface's height (lab,
    metres) under the tip at every update, ``tip0`` the tip's height with Z retracted,
    ``extension`` the fine Z extension at the start and ``distance`` the set-point's tip-sample
    distance (metres). Raises :class:`~hardware.errors.CrashError` when the tip crashes."""
    if len(surface) % loop.substeps:
        raise ValueError(
            f"{len(surface)} updates are not a whole number of pixels of {loop.substeps}"
        )
    samples = len(surface) // loop.substeps
    target = tip0 - surface - distance
    g = loop.gain
    exts = lfilter([g], [1.0, g - 1.0], target, zi=[(1.0 - g) * extension])[0]
    before = tip0 - np.concatenate([[extension], exts[:-1]]) - surface
    linear = (
        not np.any((before > loop.branch_end) & (before - distance > loop.max_step))
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
    """:func:`follow_line` update by update, with the slew limit, the range and the crash."""
    sub = loop.substeps
    line = np.zeros(samples)
    lags = np.empty(samples * sub)
    saturated = False
    for k in range(samples * sub):
        dist = tip0 - ext - surface[k]
        error = dist - distance
        if dist > loop.branch_end:
            error = min(error, loop.max_step)
        ext = min(max(ext + loop.gain * error, 0.0), loop.zrange)
        if ext in (0.0, loop.zrange):
            saturated = True
        if tip0 - ext - surface[k] < loop.crash_depth:
            raise CrashError(
                "the tip crashed into the surface: the scan is too fast for the force "
                "loop here (lower the line rate)"
            )
        line[k // sub] += (tip0 - ext) / sub
        lags[k] = tip0 - ext - surface[k] - distance  # what the loop's update left
    return LoopLine(line, ext, held_error(lags), saturated)


def held_error(lags: FloatArray) -> float:
    """The error a loop's updates ``lags`` (metres) stood at or above for a quarter of them."""
    return float(np.quantile(np.abs(lags), 0.75))
