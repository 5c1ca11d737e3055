"""Procedures above the drivers: landing, retract, one patch of a mosaic.

They use only the role Protocols, so they run unchanged on the real instrument and on the
simulated one. Every failure is a typed error an operator can read; whatever happens, the tip
ends withdrawn (the callers put the instrument in its safe state).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hardware.errors import (
    CrashError,
    Interrupted,
    NoSurfaceError,
    ProcedureError,
    SafeStateError,
    SaturationError,
)
from hardware.protocols import (
    ForceLoop,
    LineRecorder,
    PatchScanner,
    PositionerAxis,
    ProbeSignal,
    ScanLines,
)
from hardware.raster import FineRaster, linearize_rows, preposition, raster_patch, wait_stopped

FloatArray = NDArray[np.float64]

__all__ = [
    "CrashError",
    "Interrupted",
    "LandingConfig",
    "NoSurfaceError",
    "ProcedureError",
    "SafeStateError",
    "SaturationError",
    "acquire_patch",
    "land",
    "linearize_rows",
    "move_stage",
    "preposition",
    "raster_patch",
    "retract",
    "safe_state",
    "sample_origin",
]


@dataclass(frozen=True)
class LandingConfig:
    """Woodpecker landing: fine approach with the loop engaged, coarse steps in between.

    setpoint : Δf to land at, Hz.
    steps : coarse Z steps per cycle (their travel must stay well inside the fine range).
    amplitude, frequency : of the coarse steps.
    max_cycles : give up ("no surface") after this many cycles.
    """

    setpoint: float = 10.0
    steps: int = 6
    amplitude: int = 2000
    frequency: int = 1000
    max_cycles: int = 300


@dataclass(frozen=True)
class LandingReport:
    cycles: int
    frequency_shift: float


def land(
    z: PositionerAxis, loop: ForceLoop, probe: ProbeSignal, config: LandingConfig | None = None
) -> LandingReport:
    """Bring the tip to the surface at the set-point; the loop stays engaged on success.

    Each cycle engages the loop, which extends Z in fine mode toward the set-point. If it
    saturates fully extended the surface is out of reach: withdraw, step Z down a few coarse
    steps (never while extended), and try again. Saturating retracted means the surface is
    closer than the set-point even with Z pulled back: step up one cycle and retry.
    """
    cfg = config or LandingConfig()
    loop.withdraw()
    travelled = 0  # coarse steps towards the sample so far
    began = z.position()  # None without a sensor
    for cycle in range(1, cfg.max_cycles + 1):
        loop.engage(cfg.setpoint)
        if not probe.locked():
            loop.withdraw()
            raise CrashError("the PLL lost lock while landing: the tip may have crashed")
        if not loop.saturated():
            _centre_fine_range(z, loop, probe, cfg)
            return LandingReport(cycle, probe.frequency_shift())
        extended = z.fine_extension() > 0.5 * z.fine_range
        loop.withdraw()
        steps = cfg.steps if extended else -cfg.steps
        z.step(steps, amplitude=cfg.amplitude, frequency=cfg.frequency)
        wait_stopped(z)
        travelled += steps
    # give up with the tip back where the landing began, not deep down in Z: closed loop on
    # the sensor, else twice the steps (steps back are shorter; the end stop is harmless)
    if travelled > 0:
        if began is not None:
            z.move_to(began)
        else:
            z.step(-2 * travelled, amplitude=cfg.amplitude, frequency=cfg.frequency)
        wait_stopped(z)
    raise NoSurfaceError(
        f"no surface within {cfg.max_cycles} landing cycles ({travelled} coarse steps down): "
        "check the sample height and the tip; Z is back where the landing began"
    )


def _centre_fine_range(
    z: PositionerAxis, loop: ForceLoop, probe: ProbeSignal, cfg: LandingConfig
) -> None:
    """Step Z so that the locked fine extension sits mid-range, with room up and down.

    First contact happens near full extension. One known coarse cycle (loop withdrawn) and
    a re-engage measure the step size from the change of the locked extension; then the
    remaining offset is stepped away. Every coarse move happens withdrawn.
    """
    mid = 0.5 * z.fine_range
    first = z.fine_extension()
    if first < 0.7 * z.fine_range:
        return
    loop.withdraw()
    z.step(cfg.steps, amplitude=cfg.amplitude, frequency=cfg.frequency)
    wait_stopped(z)
    loop.engage(cfg.setpoint)
    if not probe.locked():
        loop.withdraw()
        raise CrashError("the PLL lost lock while centring Z after landing")
    second = z.fine_extension()
    step = (first - second) / cfg.steps
    if loop.saturated() or step <= 0:
        return  # no usable measurement: stay where the loop holds
    n = round((second - mid) / step)
    if n > 0:
        loop.withdraw()
        z.step(n, amplitude=cfg.amplitude, frequency=cfg.frequency)
        wait_stopped(z)
        loop.engage(cfg.setpoint)
        if not probe.locked():
            loop.withdraw()
            raise CrashError("the PLL lost lock while centring Z after landing")


def retract(
    z: PositionerAxis, loop: ForceLoop | None, *, steps: int = 40, amplitude: int = 2000
) -> None:
    """Withdraw the loop (if there is one), then pull Z back in stepping mode."""
    if loop is not None:
        loop.withdraw()
    z.step(-steps, amplitude=amplitude, frequency=1000)
    wait_stopped(z)


def scan_start(
    x: PositionerAxis, y: PositionerAxis, size: tuple[float, float]
) -> tuple[float, float]:
    """Fine-mode position of a patch's first pixel: the raster is centred in the fine range."""
    return (x.fine_range - size[0]) / 2, (y.fine_range - size[1]) / 2


def move_stage(
    stage_x: PositionerAxis,
    stage_y: PositionerAxis,
    x: PositionerAxis,
    y: PositionerAxis,
    *,
    origin: tuple[float, float],
    size: tuple[float, float],
) -> None:
    """Move the sample stage (stepping mode, closed loop on its sensors) so that the patch
    with sample-frame ``origin`` lies under the centred raster; wait until it stops."""
    start = scan_start(x, y, size)
    stage_x.move_to(start[0] - origin[0])
    stage_y.move_to(start[1] - origin[1])
    wait_stopped(stage_x)
    wait_stopped(stage_y)


def sample_origin(
    lines: ScanLines,
    stage_x: PositionerAxis,
    stage_y: PositionerAxis,
    *,
    planned: tuple[float, float],
    size: tuple[float, float],
    x: PositionerAxis,
    y: PositionerAxis,
) -> tuple[float, float]:
    """Nominal sample-frame origin of scanned lines: the raster origin minus the stage
    position its sensors read (the planned target where an axis has no sensor)."""
    start = scan_start(x, y, size)
    sx, sy = stage_x.position(), stage_y.position()
    return (
        lines.origin[0] - (start[0] - planned[0] if sx is None else sx),
        lines.origin[1] - (start[1] - planned[1] if sy is None else sy),
    )


def safe_state(
    loop: ForceLoop | None,
    z: PositionerAxis,
    axes: Sequence[PositionerAxis],
    *,
    scanner: PatchScanner | None = None,
    attempts: int = 3,
) -> None:
    """Stop any scan, withdraw the loop, retract Z in stepping mode and stop every axis;
    confirm it.

    Tries ``attempts`` times (a link may recover); raises :class:`SafeStateError` naming
    what could not be done when the state cannot be confirmed.
    """
    problem = "not tried"
    for _ in range(max(1, attempts)):
        try:
            if scanner is not None:
                scanner.stop()
            if loop is not None:
                loop.withdraw()
            for axis in axes:
                axis.stop()
            retract(z, loop)
            for axis in (*axes, z):
                wait_stopped(axis, polls=2000)
            if loop is not None and loop.engaged():
                raise ProcedureError("the force loop is still engaged")
            return
        except Exception as exc:  # every failure is reported; the next attempt may succeed
            problem = f"{type(exc).__name__}: {exc}"
    raise SafeStateError(
        f"safe state not confirmed ({problem}): check the instrument before resetting the run"
    )


@dataclass(frozen=True)
class PatchResult:
    """One scanned patch: its lines and its nominal sample-frame origin (metres)."""

    lines: ScanLines
    origin: tuple[float, float]


def acquire_patch(
    *,
    stage_x: PositionerAxis,
    stage_y: PositionerAxis,
    x: PositionerAxis,
    y: PositionerAxis,
    z: PositionerAxis,
    loop: ForceLoop,
    probe: ProbeSignal,
    recorder: LineRecorder,
    origin: tuple[float, float],
    size: tuple[float, float],
    pixels: tuple[int, int],
    line_rate: float,
    landing: LandingConfig | None = None,
) -> PatchResult:
    """Move the sample stage, land, raster in fine mode and retract: one patch.

    ``x``, ``y`` and ``z`` are the probe robot's axes. Whatever fails, the tip is retracted
    before the error propagates. (The acquisition server runs the same steps one by one.)
    """
    scanner = FineRaster(x, y, recorder, loop)
    move_stage(stage_x, stage_y, x, y, origin=origin, size=size)
    scanner.prepare(size=size, pixels=pixels)
    try:
        land(z, loop, probe, landing)
        lines = scanner.scan(size=size, pixels=pixels, line_rate=line_rate)
    finally:
        retract(z, loop)
    lines.require_unsaturated()
    nominal = sample_origin(lines, stage_x, stage_y, planned=origin, size=size, x=x, y=y)
    return PatchResult(lines, nominal)
