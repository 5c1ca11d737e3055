"""A :class:`~hardware.protocols.PositionerAxis` on one channel of an MCS controller."""

from __future__ import annotations

from dataclasses import dataclass

from hardware.errors import ProcedureError
from hardware.smaract_errors import NoSensorError
from hardware.smaract_mcs import MAX_LEVEL, AxisStatus, MCSController

#: The sample stage's travel on each axis, metres (its soft limits).
STAGE_TRAVEL = (-6e-3, 6e-3)


class TravelError(ProcedureError):
    """A move past an axis's travel, refused before anything moves."""


@dataclass(frozen=True)
class FineCalibration:
    """How a channel's fine-mode voltage level maps to metres: ``extension = gain * level``.

    Measured per axis (piezo gains differ by tens of per cent); ``range`` is the extension at
    full level, metres.
    """

    range: float = 1.6e-6

    @property
    def metres_per_level(self) -> float:
        return self.range / MAX_LEVEL

    def level(self, extension: float) -> int:
        """The voltage level for ``extension`` metres; ValueError outside the fine range."""
        if not 0.0 <= extension <= self.range * (1 + 1e-9):
            raise ValueError(
                f"fine extension {extension * 1e9:.1f} nm is outside 0..{self.range * 1e9:.0f} nm"
            )
        return min(MAX_LEVEL, round(extension / self.metres_per_level))


class MCSAxis:
    """One channel of an :class:`MCSController` as a positioner axis.

    Parameters
    ----------
    controller : MCSController
    channel : int
    name : str
    calibration : FineCalibration
        This axis's fine-mode gain.
    has_sensor : bool
        Whether the channel has a position sensor.
    travel : (low, high), optional
        Soft limits of a closed-loop move, metres: a move past them is refused
        (:class:`TravelError`) before anything is sent.
    """

    def __init__(
        self,
        controller: MCSController,
        channel: int,
        *,
        name: str,
        calibration: FineCalibration | None = None,
        has_sensor: bool = True,
        travel: tuple[float, float] | None = None,
    ) -> None:
        self.controller = controller
        self.channel = channel
        self.name = name
        self.calibration = calibration or FineCalibration()
        self.has_sensor = has_sensor
        self.travel = travel

    @property
    def fine_range(self) -> float:
        return self.calibration.range

    def position(self) -> float | None:
        if not self.has_sensor:
            return None
        try:
            return self.controller.position(self.channel)
        except NoSensorError:
            return None

    def status(self) -> AxisStatus:
        return self.controller.status(self.channel)

    def step(self, steps: int, *, amplitude: int, frequency: int) -> None:
        self.controller.step(self.channel, steps, amplitude=amplitude, frequency=frequency)

    def move_to(self, position: float, *, hold: float = 0.0) -> None:
        if self.travel is not None:
            lo, hi = self.travel
            if not lo <= position <= hi:  # NaN too
                raise TravelError(
                    f"{self.name}: a move to {position * 1e3:.6g} mm is past its travel "
                    f"{lo * 1e3:g}..{hi * 1e3:g} mm: refused, nothing moved"
                )
        self.controller.move_absolute(self.channel, position, hold_ms=round(hold * 1000))

    def fine_to(self, extension: float, *, speed: float) -> None:
        if not speed > 0:
            raise ValueError(f"fine speed must be positive, got {speed}")
        levels_per_s = max(1, round(speed / self.calibration.metres_per_level))
        self.controller.scan_absolute(
            self.channel, self.calibration.level(extension), speed=levels_per_s
        )

    def fine_extension(self) -> float:
        return self.controller.voltage_level(self.channel) * self.calibration.metres_per_level

    def stop(self) -> None:
        self.controller.stop(self.channel)
