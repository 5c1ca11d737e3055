"""Procedures above the drivers: landing, retract, one patch of a mosaic.

They use only the role Protocols, so they run unchanged on the real instrument and on the
simulated one. Every failure is a typed error an operator can read; whatever happens, the tip
ends withdrawn (the callers put the instrument in its safe state).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
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
from hardware.protocols import ForceLoop, LineRecorder, PositionerAxis, ProbeSignal, ScanLines
from hardware.smaract_mcs import AxisStatus

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


def wait_stopped(axis: PositionerAxis, *, polls: int = 100_000) -> None:
    """Poll until ``axis`` has stopped (or finished holding)."""
    for _ in range(polls):
        if axis.status() in (AxisStatus.STOPPED, AxisStatus.HOLDING):
            return
    raise ProcedureError(f"{axis.name} did not stop")


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


def preposition(
    x: PositionerAxis, y: PositionerAxis, *, size: tuple[float, float], pixels: tuple[int, int]
) -> None:
    """Put the fine axes where a raster of ``size`` starts, Y arriving from below.

    Piezo hysteresis depends on the direction of the last move: every row of a raster is
    reached going up, so the first must be too (down to the bottom of the range, then up).
    Done before landing, the creep of this long move relaxes while the tip approaches.
    """
    w, h = size
    start_x = (x.fine_range - w) / 2
    first_row = (y.fine_range - h) / 2 + h / pixels[1] / 2
    if abs(y.fine_extension() - first_row) > 1e-10:
        y.fine_to(0.0, speed=y.fine_range)
        wait_stopped(y)
        y.fine_to(first_row, speed=y.fine_range)
    x.fine_to(start_x, speed=10 * x.fine_range)
    wait_stopped(x)
    wait_stopped(y)


def raster_patch(
    x: PositionerAxis,
    y: PositionerAxis,
    recorder: LineRecorder,
    *,
    size: tuple[float, float],
    pixels: tuple[int, int],
    line_rate: float,
    stop: Callable[[], bool] | None = None,
) -> ScanLines:
    """Raster a patch in fine mode, trace only, with the force loop engaged.

    The patch is centred in the fine range. Each line: Y steps to the line and X flies back
    to its start (waiting until both stop), then X ramps across at the line speed while the
    recorder samples the tip height, one line every ``1 / line_rate`` seconds. ``stop`` is
    polled before every line; when it returns true the scan ends with :class:`Interrupted`.
    """
    nx, ny = pixels
    w, h = size
    fine = min(x.fine_range, y.fine_range)
    if nx < 2 or ny < 2:
        raise ValueError(f"need at least 2 x 2 pixels, got {pixels}")
    if not (0 < w <= fine and 0 < h <= fine):
        raise ValueError(f"a patch must fit the fine range ({fine * 1e6:.2f} µm), got {size}")
    if not line_rate > 0:
        raise ValueError(f"line rate must be positive, got {line_rate}")
    # The X ramp spans the patch width exactly, centred in the fine range: pixel k is what
    # the recorder integrates over the k-th of nx equal time slices, so its centre lies at
    # start + (k + 1/2) dx. Rows sit at the centres of their slices the same way.
    dx, dy = w / nx, h / ny
    start_x, start_y = (x.fine_range - w) / 2, (y.fine_range - h) / 2
    x0, y0 = start_x + dx / 2, start_y + dy / 2
    preposition(x, y, size=size, pixels=pixels)
    line_time = 1.0 / line_rate
    heights = np.full((ny, nx), np.nan)
    times = np.zeros(ny)
    row_y = np.full(ny, np.nan)  # where the Y sensor says each row was
    for i in range(ny):
        if stop is not None and stop():
            raise Interrupted(f"scan stopped on request after {i} of {ny} lines")
        y.fine_to(y0 + i * dy, speed=y.fine_range)
        x.fine_to(start_x, speed=10 * x.fine_range)
        wait_stopped(x)
        wait_stopped(y)
        reading = y.position()
        row_y[i] = np.nan if reading is None else reading
        x.fine_to(start_x + w, speed=w / line_time)
        heights[i], times[i] = recorder.record_line(nx, line_time)
    return ScanLines(
        heights=linearize_rows(heights, row_y, dy),
        line_times=times,
        origin=(x0, y0),
        pixel_size=(dx, dy),
        row_readings=row_y,
    )


def linearize_rows(heights: FloatArray, row_y: FloatArray, dy: float) -> FloatArray:
    """Resample rows from where the Y sensor read them to an even pitch ``dy``.

    The fine mode's hysteresis and creep bend the row positions by several nm over a patch
    (the same way in every patch, so a rigid merge cannot undo it). The sensor reads each
    row's position with ~1 nm noise; a cubic in the row index keeps the bend and drops the
    noise. Without readings (no sensor) the rows are returned as they are.

    heights : (ny, nx) metres; row_y : (ny,) sensor readings, metres (NaN where unread).
    """
    ny = heights.shape[0]
    index = np.arange(ny, dtype=np.float64)
    ok = np.isfinite(row_y)
    if ny < 8 or ok.sum() < ny:
        return heights
    fit = np.polynomial.Polynomial.fit(index, row_y, deg=3)
    where = (fit(index) - fit(0.0)) / dy  # rows, in nominal row units from the first
    if not np.all(np.diff(where) > 0) or abs(where[-1] - (ny - 1)) > 0.2 * ny:
        return heights  # not a plausible raster: keep the data unchanged
    out = np.empty_like(heights)
    for j in range(heights.shape[1]):
        out[:, j] = np.interp(index, where, heights[:, j])  # a fraction of a row at the ends
    return out


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


def scan(
    x: PositionerAxis,
    y: PositionerAxis,
    loop: ForceLoop,
    recorder: LineRecorder,
    *,
    size: tuple[float, float],
    pixels: tuple[int, int],
    line_rate: float,
    stop: Callable[[], bool] | None = None,
) -> ScanLines:
    """:func:`raster_patch`, then fail if Z saturated on the way (the data would be clipped)."""
    lines = raster_patch(x, y, recorder, size=size, pixels=pixels, line_rate=line_rate, stop=stop)
    if loop.saturated():
        raise SaturationError(
            "Z ran out of its fine range during the scan: the patch is too tall or tilted "
            "for one scan; use smaller patches or level the sample"
        )
    return lines


def safe_state(
    loop: ForceLoop | None,
    z: PositionerAxis,
    axes: Sequence[PositionerAxis],
    *,
    attempts: int = 3,
) -> None:
    """Withdraw the loop, retract Z in stepping mode and stop every axis; confirm it.

    Tries ``attempts`` times (a link may recover); raises :class:`SafeStateError` naming
    what could not be done when the state cannot be confirmed.
    """
    problem = "not tried"
    for _ in range(max(1, attempts)):
        try:
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
    move_stage(stage_x, stage_y, x, y, origin=origin, size=size)
    preposition(x, y, size=size, pixels=pixels)
    try:
        land(z, loop, probe, landing)
        lines = scan(x, y, loop, recorder, size=size, pixels=pixels, line_rate=line_rate)
    finally:
        retract(z, loop)
    nominal = sample_origin(lines, stage_x, stage_y, planned=origin, size=size, x=x, y=y)
    return PatchResult(lines, nominal)
