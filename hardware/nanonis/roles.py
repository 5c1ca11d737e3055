"""The instrument's roles on a Nanonis controller: probe signal, force loop, axes, approach.

Conventions (SI units). Nanonis reports Z with the high limit as the withdrawn tip; the
roles speak the project's fine-mode language, where an axis's extension runs from 0
(retracted) to its fine range (fully extended towards the sample): ``extension = high - Z``.
The scan piezos' X and Y are 0 at the middle of their range in Nanonis; here a fine extension
runs from 0 to the range, so ``extension = XY + range / 2``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

from hardware.errors import CrashError, ProcedureError
from hardware.nanonis.client import NanonisClient
from hardware.procedures import LandingReport
from hardware.smaract_mcs import AxisStatus


@dataclass(frozen=True)
class ZPiezo:
    """The Z piezo's limits as the controller reports them (metres, high = withdrawn)."""

    high: float
    low: float

    @property
    def range(self) -> float:
        return self.high - self.low

    def at_limit(self, z: float, *, tolerance: float = 2e-3) -> bool:
        """Whether ``z`` sits at either limit (within ``tolerance`` of the range)."""
        margin = tolerance * self.range
        return z >= self.high - margin or z <= self.low + margin


class NanonisProbe:
    """:class:`~hardware.protocols.ProbeSignal` on the oscillation controller's PLL.

    Locked means Δf inside the PLL's frequency range and, where the controller has an
    amplitude signal, the amplitude above half its set-point (a crashed or stuck fork stops
    oscillating).
    """

    def __init__(self, client: NanonisClient, *, modulator: int = 1) -> None:
        self.client = client
        self.modulator = modulator
        self.range = client.frequency_range(modulator)
        self.amplitude_target = client.amplitude_setpoint(modulator)
        names = client.signal_names()
        found = [i for i, n in enumerate(names) if "Amplitude" in n and "OC" in n]
        self.amplitude_signal: int | None = found[0] if found else None

    def frequency_shift(self) -> float:
        return self.client.frequency_shift(self.modulator)

    def amplitude(self) -> float:
        if self.amplitude_signal is None:
            return self.amplitude_target
        return self.client.signal_value(self.amplitude_signal)

    def locked(self) -> bool:
        if not abs(self.frequency_shift()) < self.range:
            return False
        return self.amplitude_signal is None or self.amplitude() > 0.5 * self.amplitude_target


class NanonisZLoop:
    """:class:`~hardware.protocols.ForceLoop` on the Z controller (set-point in Hz on Δf).

    Engaging waits until Z settles: successive readings ``poll`` seconds apart within
    ``settle_tolerance`` metres of each other, or Z at a limit, for at most ``settle_timeout``.
    """

    def __init__(
        self,
        client: NanonisClient,
        z: ZPiezo,
        *,
        poll: float = 0.005,
        settle_tolerance: float = 0.5e-9,
        settle_timeout: float = 2.0,
    ) -> None:
        self.client, self.z = client, z
        self.poll = poll
        self.settle_tolerance = settle_tolerance
        self.settle_timeout = settle_timeout

    def engage(self, setpoint: float) -> None:
        self.client.set_setpoint(setpoint)
        self.client.z_controller(True)
        deadline = time.monotonic() + self.settle_timeout
        last = self.client.z_position()
        while time.monotonic() < deadline and not self.z.at_limit(last):
            time.sleep(self.poll)
            now = self.client.z_position()
            if abs(now - last) < self.settle_tolerance:
                return
            last = now

    def withdraw(self) -> None:
        self.client.withdraw(wait=True)

    def engaged(self) -> bool:
        return self.client.z_controller_on()

    def saturated(self) -> bool:
        return self.engaged() and self.z.at_limit(self.client.z_position())

    def tracking_error(self) -> float:
        """Not reported: the scan module records Z, not the loop's error."""
        return math.nan


class NanonisZAxis:
    """The probe's Z as a :class:`~hardware.protocols.PositionerAxis`: fine mode on the Z
    piezo, stepping mode on the coarse motor module (``approach`` is the direction towards
    the sample, ``Z-`` on most set-ups). The motor's step amplitude and frequency are the
    controller's own settings; it has no position sensor here."""

    name = "nanonis z"

    def __init__(
        self, client: NanonisClient, z: ZPiezo, *, approach: str = "Z-", group: int = 0
    ) -> None:
        if approach not in ("Z-", "Z+"):
            raise ValueError(f"approach must be Z- or Z+, got {approach!r}")
        self.client, self.z, self.group = client, z, group
        self.towards, self.away = approach, ("Z+" if approach == "Z-" else "Z-")

    @property
    def fine_range(self) -> float:
        return self.z.range

    def position(self) -> float | None:
        return None

    def status(self) -> AxisStatus:
        return AxisStatus.STOPPED  # every move waits until it is done

    def step(self, steps: int, *, amplitude: int, frequency: int) -> None:
        direction = self.towards if steps > 0 else self.away
        remaining = abs(steps)
        while remaining:
            n = min(remaining, 0xFFFF)
            self.client.motor_move(direction, n, group=self.group)
            remaining -= n

    def move_to(self, position: float, *, hold: float = 0.0) -> None:
        raise ProcedureError("the Nanonis Z motor has no position sensor: move it in steps")

    def fine_to(self, extension: float, *, speed: float) -> None:
        if not 0 <= extension <= self.z.range:
            raise ValueError(f"Z extension {extension:g} m is outside 0..{self.z.range:g} m")
        self.client.set_z_position(self.z.high - extension)

    def fine_extension(self) -> float:
        return self.z.high - self.client.z_position()

    def stop(self) -> None:
        self.client.motor_stop()


class NanonisScanAxis:
    """One scan piezo (X or Y) as a :class:`~hardware.protocols.PositionerAxis`: fine mode
    through the follow-me module; no stepping mode, no sensor."""

    def __init__(self, client: NanonisClient, axis: int, fine_range: float) -> None:
        if axis not in (0, 1):
            raise ValueError(f"axis must be 0 (X) or 1 (Y), got {axis}")
        self.client, self.axis, self._range = client, axis, fine_range
        self.name = f"nanonis scan {'xy'[axis]}"

    @property
    def fine_range(self) -> float:
        return self._range

    def position(self) -> float | None:
        return None

    def status(self) -> AxisStatus:
        return AxisStatus.STOPPED

    def step(self, steps: int, *, amplitude: int, frequency: int) -> None:
        raise ProcedureError(f"{self.name} has no stepping mode: the sample stage moves coarse")

    def move_to(self, position: float, *, hold: float = 0.0) -> None:
        raise ProcedureError(f"{self.name} has no sensor: use its fine mode")

    def fine_to(self, extension: float, *, speed: float) -> None:
        if not 0 <= extension <= self._range:
            raise ValueError(f"{self.name}: {extension:g} m is outside 0..{self._range:g} m")
        xy = list(self.client.tip_xy())
        xy[self.axis] = extension - self._range / 2
        self.client.set_tip_speed(speed)
        self.client.move_tip(xy[0], xy[1])

    def fine_extension(self) -> float:
        return self.client.tip_xy()[self.axis] + self._range / 2

    def stop(self) -> None:
        self.client.stop_tip()


class NanonisMotorAxis:
    """A sample-stage axis (X or Y) on the controller's coarse motor module: open-loop steps
    and, where the motor has sensors, closed-loop moves and positions."""

    def __init__(self, client: NanonisClient, axis: int, *, group: int = 0) -> None:
        if axis not in (0, 1):
            raise ValueError(f"axis must be 0 (X) or 1 (Y), got {axis}")
        self.client, self.axis, self.group = client, axis, group
        self.name = f"nanonis motor {'xy'[axis]}"

    @property
    def fine_range(self) -> float:
        return 0.0

    def position(self) -> float | None:
        return self.client.motor_position(group=self.group)[self.axis]

    def status(self) -> AxisStatus:
        return AxisStatus.STOPPED

    def step(self, steps: int, *, amplitude: int, frequency: int) -> None:
        direction = ("X+", "X-", "Y+", "Y-")[2 * self.axis + (steps < 0)]
        self.client.motor_move(direction, min(abs(steps), 0xFFFF), group=self.group)

    def move_to(self, position: float, *, hold: float = 0.0) -> None:
        target = list(self.client.motor_position(group=self.group))
        target[self.axis] = position
        self.client.motor_move_to((target[0], target[1], target[2]), group=self.group)

    def fine_to(self, extension: float, *, speed: float) -> None:
        raise ProcedureError(f"{self.name} has no fine mode")

    def fine_extension(self) -> float:
        return 0.0

    def stop(self) -> None:
        self.client.motor_stop()


def auto_approach(
    client: NanonisClient,
    loop: NanonisZLoop,
    probe: NanonisProbe,
    *,
    setpoint: float = 10.0,
    timeout: float = 600.0,
    poll: float = 0.05,
) -> LandingReport:
    """Land with the controller's own auto-approach; the loop stays engaged on success."""
    client.set_setpoint(setpoint)
    client.auto_approach(True)
    deadline = time.monotonic() + timeout
    polls = 0
    try:
        while client.auto_approach_running():
            polls += 1
            if time.monotonic() > deadline:
                raise ProcedureError(f"the auto-approach did not end within {timeout:g} s")
            time.sleep(poll)
    except BaseException:
        client.auto_approach(False)
        loop.withdraw()
        raise
    if not client.z_controller_on():
        raise ProcedureError(
            "the auto-approach ended without the Z controller on: no surface found (check "
            "the sample height, the tip and the approach direction)"
        )
    if not probe.locked():
        loop.withdraw()
        raise CrashError("the PLL lost lock during the auto-approach: the tip may have crashed")
    return LandingReport(polls, probe.frequency_shift())
