"""The fine-mode raster: a patch scanned by the probe robot's own X and Y piezos.

On the simulated AFM-in-SEM (and any set-up whose AFM controller records lines while the
positioners move) the software rasters the patch itself, line by line, on the robot's fine
axes; :class:`FineRaster` offers it as a :class:`~hardware.protocols.PatchScanner`. Where the
AFM controller has its own scan generator (Nanonis), its scanner fills the same role.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from hardware.errors import Interrupted, ProcedureError
from hardware.protocols import ForceLoop, LineRecorder, PositionerAxis, ScanLines
from hardware.smaract_mcs import AxisStatus

FloatArray = NDArray[np.float64]


def wait_stopped(axis: PositionerAxis, *, polls: int = 100_000) -> None:
    """Poll until ``axis`` has stopped (or finished holding)."""
    for _ in range(polls):
        if axis.status() in (AxisStatus.STOPPED, AxisStatus.HOLDING):
            return
    raise ProcedureError(f"{axis.name} did not stop")


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
    loop: ForceLoop | None = None,
) -> ScanLines:
    """Raster a patch in fine mode, trace only, with the force loop engaged.

    The patch is centred in the fine range. Each line: Y steps to the line and X flies back
    to its start (waiting until both stop), then X ramps across at the line speed while the
    recorder samples the tip height, one line every ``1 / line_rate`` seconds. ``stop`` is
    polled before every line; when it returns true the scan ends with :class:`Interrupted`.
    With the force ``loop``, each line's saturation and tracking error are recorded too.
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
    saturated = np.zeros(ny, dtype=bool)
    tracking = np.full(ny, np.nan)
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
        if loop is not None:
            saturated[i], tracking[i] = loop.saturated(), loop.tracking_error()
    return ScanLines(
        heights=linearize_rows(heights, row_y, dy),
        line_times=times,
        origin=(x0, y0),
        pixel_size=(dx, dy),
        row_readings=row_y,
        saturated=saturated if loop is not None else None,
        tracking=tracking if loop is not None else None,
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


class FineRaster:
    """:class:`~hardware.protocols.PatchScanner` on fine axes ``x``, ``y`` and a line
    ``recorder``; ``loop`` tells, line by line, whether Z saturated and how well it tracked."""

    def __init__(
        self, x: PositionerAxis, y: PositionerAxis, recorder: LineRecorder, loop: ForceLoop
    ) -> None:
        self.x, self.y, self.recorder, self.loop = x, y, recorder, loop

    @property
    def fine_range(self) -> tuple[float, float]:
        return self.x.fine_range, self.y.fine_range

    def prepare(self, *, size: tuple[float, float], pixels: tuple[int, int]) -> None:
        preposition(self.x, self.y, size=size, pixels=pixels)

    def scan(
        self,
        *,
        size: tuple[float, float],
        pixels: tuple[int, int],
        line_rate: float,
        stop: Callable[[], bool] | None = None,
    ) -> ScanLines:
        """:func:`raster_patch`, each line's saturation and tracking error recorded (the
        caller judges them: :meth:`~hardware.protocols.ScanLines.require_unsaturated`, or a
        quality gate)."""
        return raster_patch(
            self.x,
            self.y,
            self.recorder,
            size=size,
            pixels=pixels,
            line_rate=line_rate,
            stop=stop,
            loop=self.loop,
        )

    def stop(self) -> None:
        self.x.stop()
        self.y.stop()
