"""One typed Protocol per hardware role (SI units: metres, seconds, hertz).

Real drivers and the simulated instrument both implement these, so the procedures above them
(landing, retract, raster) and the server run unchanged on either: SmarAct MCS positioners,
a Nanonis controller (probe signal, force loop, patch scanner) or the simulated AFM-in-SEM.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from hardware.errors import SaturationError
from hardware.smaract_mcs import AxisStatus

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: A line whose loop error (:meth:`ForceLoop.tracking_error`) is above this, metres, is
#: mistracked: a loop that follows the surface lags by a few nm, briefly more past a step
#: down; a tip that lost the surface (parachuting) stays tens to hundreds of nm off.
TRACKING_BOUND = 20e-9


@runtime_checkable
class PositionerAxis(Protocol):
    """One stick-slip axis: stepping mode (coarse, long range) and fine mode (scan)."""

    name: str

    def position(self) -> float | None:
        """Sensor read-back, metres; None for an axis without sensor."""
        ...

    def status(self) -> AxisStatus:
        """The axis's status code as the controller reports it (stopped, stepping, holding...)."""
        ...

    def step(self, steps: int, *, amplitude: int, frequency: int) -> None:
        """Open-loop steps (sign gives the direction)."""
        ...

    def move_to(self, position: float, *, hold: float = 0.0) -> None:
        """Closed-loop move to ``position`` metres (needs a sensor)."""
        ...

    def fine_to(self, extension: float, *, speed: float) -> None:
        """Fine mode to ``extension`` metres of the fine range, at ``speed`` m/s."""
        ...

    def fine_extension(self) -> float:
        """Current fine-mode extension, metres (from the voltage level and calibration)."""
        ...

    @property
    def fine_range(self) -> float:
        """Fine-mode range, metres."""
        ...

    def stop(self) -> None:
        """Stop the axis at once (part of the safe state)."""
        ...


@runtime_checkable
class ProbeSignal(Protocol):
    """The self-sensing probe's PLL: frequency shift and amplitude."""

    def frequency_shift(self) -> float:
        """Δf, hertz (negative when attractive, rising through zero into repulsion)."""
        ...

    def amplitude(self) -> float:
        """Oscillation amplitude, metres."""
        ...

    def locked(self) -> bool:
        """Whether the PLL follows the resonance."""
        ...


@runtime_checkable
class ForceLoop(Protocol):
    """The Z feedback on Δf."""

    def engage(self, setpoint: float) -> None:
        """Regulate Z so that Δf stays at ``setpoint`` hertz."""
        ...

    def withdraw(self) -> None:
        """Open the loop and pull Z fully back in fine mode."""
        ...

    def engaged(self) -> bool:
        """Whether the Z feedback is on (the tip held on the surface)."""
        ...

    def saturated(self) -> bool:
        """True when Z hit an end of its fine range while engaged."""
        ...

    def tracking_error(self) -> float:
        """The loop's error over the last line recorded, as distance from the set-point's,
        metres: the size it kept for a quarter of the line (NaN where the controller does not
        report it)."""
        ...


@dataclass(frozen=True)
class ScanLines:
    """One raster patch as the scanner returns it.

    Attributes
    ----------
    heights
        (ny, nx) metres, rows along y, NaN where the loop lost the surface.
    line_times
        (ny,) simulated or wall seconds at the start of every line.
    origin
        fine-mode (x, y) of pixel (0, 0) in the probe robot's fine frame, metres; the
        sample position is this minus the sample stage's position.
    pixel_size
        (dx, dy) metres.
    """

    heights: FloatArray
    line_times: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    #: (ny,) the Y sensor's reading at each row, metres (NaN without a sensor); the heights
    #: are already resampled from these positions to the even pitch
    row_readings: FloatArray | None = None
    #: (ny,) whether Z stood at an end of its range on each line (None: not known)
    saturated: BoolArray | None = None
    #: (ny,) the loop's error on each line, metres (None: not reported)
    tracking: FloatArray | None = None

    def saturated_lines(self) -> int:
        """How many lines Z saturated on (their heights are clipped there)."""
        return 0 if self.saturated is None else int(np.count_nonzero(self.saturated))

    def mistracked_lines(self, bound: float = TRACKING_BOUND) -> int:
        """How many lines the loop's error exceeded ``bound`` metres on (the tip lost the
        surface: parachuting after a step down, or a scan too fast for the loop)."""
        if self.tracking is None:
            return 0
        return int(np.count_nonzero(self.tracking > bound))

    def require_unsaturated(self) -> None:
        """Raise :class:`~hardware.errors.SaturationError` if Z saturated on any line (for
        callers with no quality gate to judge the patch)."""
        count = self.saturated_lines()
        if count:
            raise SaturationError(
                f"Z reached a limit of its range on {count} of {len(self.heights)} lines: the "
                "patch is too tall or tilted for one scan, or the surface fell away; use "
                "smaller patches or level the sample"
            )


@runtime_checkable
class LineRecorder(Protocol):
    """The AFM controller's acquisition: tip heights sampled while the axes move."""

    def record_line(self, samples: int, duration: float) -> tuple[FloatArray, float]:
        """Sample the tip height ``samples`` times, evenly over ``duration`` seconds, with the
        force loop engaged; return the heights (metres) and the start time (seconds)."""
        ...


@runtime_checkable
class PatchScanner(Protocol):
    """The raster of one patch, centred in the fine range, with the force loop engaged.

    Filled by the software's own raster on the fine axes (:class:`hardware.raster.FineRaster`)
    or by the AFM controller's scan generator (:class:`hardware.nanonis.scanner.NanonisScanner`).
    """

    @property
    def fine_range(self) -> tuple[float, float]:
        """The scan range along x and y, metres."""
        ...

    def prepare(self, *, size: tuple[float, float], pixels: tuple[int, int]) -> None:
        """Before landing: program the patch and put the tip where its raster starts."""
        ...

    def scan(
        self,
        *,
        size: tuple[float, float],
        pixels: tuple[int, int],
        line_rate: float,
        stop: Callable[[], bool] | None = None,
    ) -> ScanLines:
        """Scan ``pixels`` = (nx, ny) over ``size`` (metres) at ``line_rate`` lines per second;
        ``stop`` is polled between lines (true ends the scan with ``Interrupted``)."""
        ...

    def stop(self) -> None:
        """Stop scanning at once (part of the safe state)."""
        ...


@dataclass(frozen=True)
class SEMImage:
    """An SEM image and where its pixels are on the stage: an affine map.

    Attributes
    ----------
    pixels
        (ny, nx) grey levels, row 0 the top line as the SEM shows it.
    origin
        stage position (metres) of pixel (0, 0)'s centre.
    pixel_size
        metres per pixel along the image's columns and rows (positive).
    matrix
        the 2 x 2 map from a pixel step (column, row) to stage metres: rotation, scale,
        shear and the rows' direction; None is ``diag(pixel_size)`` (axis-aligned, rows along
        +y: how the images of earlier versions were placed).
    """

    pixels: NDArray[np.float64]
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    matrix: tuple[tuple[float, float], tuple[float, float]] | None = None

    @property
    def map(self) -> NDArray[np.float64]:
        """The 2 x 2 pixel-to-stage matrix (``matrix``, or ``diag(pixel_size)``)."""
        if self.matrix is None:
            return np.diag(np.asarray(self.pixel_size, dtype=np.float64))
        return np.asarray(self.matrix, dtype=np.float64)

    def to_stage(self, col: float, row: float) -> tuple[float, float]:
        """Stage position of fractional pixel ``(col, row)``."""
        x, y = self.map @ np.array([col, row]) + np.asarray(self.origin)
        return float(x), float(y)

    def to_pixel(self, x: float, y: float) -> tuple[float, float]:
        """The fractional pixel ``(col, row)`` of stage position ``(x, y)``."""
        col, row = np.linalg.solve(self.map, np.array([x, y]) - np.asarray(self.origin))
        return float(col), float(row)


@dataclass(frozen=True)
class SEMFrame:
    """An SEM image as the microscope took it, in its own frame (where it lies on the sample
    stage is the SEM-to-stage calibration's to say).

    pixels : (ny, nx) grey levels, row 0 the top line of the scan (as the SEM shows it).
    pixel_size : metres per pixel (the field of view over the pixels across).
    rotation : the scan rotation, degrees (counter-clockwise, as the SEM applies it).
    stage : the SEM stage's position when it was taken: x, y, z metres.
    field : the field of view across, metres.
    dwell : seconds per pixel.
    detector : the detector's name.
    """

    pixels: NDArray[np.float64]
    pixel_size: float
    rotation: float
    stage: tuple[float, float, float]
    field: float
    dwell: float
    detector: str


@runtime_checkable
class SEM(Protocol):
    """The scanning electron microscope around the AFM."""

    def acquire(
        self, *, field: float, pixels: int, dwell: float = 1e-6, detector: str = "SE"
    ) -> SEMFrame:
        """One square frame of ``field`` metres across, ``pixels`` a side, ``dwell`` seconds a
        pixel, on ``detector``, with its geometry as the SEM reports it."""
        ...

    def view_field(self) -> float:
        """The field of view across, metres."""
        ...

    def scan_rotation(self) -> float:
        """The scan rotation, degrees counter-clockwise."""
        ...

    def stage_position(self) -> tuple[float, float, float, float, float]:
        """The SEM's own stage: x, y, z (metres), rotation and tilt (degrees)."""
        ...
