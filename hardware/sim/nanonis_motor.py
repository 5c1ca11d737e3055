"""The simulated Nanonis coarse motor module (``Motor.*``) on the simulated world's stick-slip
axes.

Directions 0-3 step the sample stage's X and Y (``X+``, ``X-``, ``Y+``, ``Y-``), 4 and 5 the
probe robot's Z (``Z-`` approaches, ``Z+`` retracts), open loop, at one step amplitude and
frequency; the closed loop moves the stage to a position on its sensors. Each command returns
once its motion is done (time moves on to it); a bad argument raises ``ValueError``, which
the controller answers with its error block (:mod:`hardware.sim.nanonis_controller`).
"""

from __future__ import annotations

from typing import Any

from hardware.sim.instrument import SimulatedAFM

#: Step amplitude and frequency of the simulated coarse motor (MCS units).
MOTOR_AMPLITUDE, MOTOR_FREQUENCY = 2000, 1000
#: Motor.StartMove direction -> (device, channel, sign).
DIRECTIONS = {
    0: ("stage", 0, 1),
    1: ("stage", 0, -1),
    2: ("stage", 1, 1),
    3: ("stage", 1, -1),
    4: ("z", 2, -1),
    5: ("z", 2, 1),
}


class MotorModule:
    """The coarse motors of the world ``afm``: the commands' handlers, each taking the decoded
    arguments and returning the reply's values."""

    def __init__(self, afm: SimulatedAFM) -> None:
        self.afm = afm

    def start_move(self, a: list[Any]) -> list[Any]:
        """Motor.StartMove: ``steps`` open-loop steps in a direction."""
        direction, steps = int(a[0]), int(a[1])
        if direction not in DIRECTIONS:
            raise ValueError(f"motor direction {direction} is not in 0..5")
        device, channel, sign = DIRECTIONS[direction]
        afm = self.afm
        axis = (afm.stage_device if device == "stage" else afm.robot_device).axes[channel]
        t = afm.clock.now()
        axis.step(sign * steps, MOTOR_AMPLITUDE, MOTOR_FREQUENCY, t)
        afm.clock.advance_to(axis.busy_until(t))
        axis.status(afm.clock.now())
        return []

    def closed_loop(self, a: list[Any]) -> list[Any]:
        """Motor.StartClosedLoop: the stage to X, Y on its sensors (absolute or relative)."""
        absolute, x, y = int(a[0]), float(a[1]), float(a[2])
        if absolute not in (0, 1):
            raise ValueError(f"absolute/relative must be 0 or 1, got {absolute}")
        t = self.afm.clock.now()
        axes = self.afm.stage_device.axes
        if not absolute:
            x, y = x + axes[0].sensor(t), y + axes[1].sensor(t)
        for axis, target in zip(axes, (x, y), strict=True):
            axis.move_to(target, 0, t)
        self.afm.clock.advance_to(max(axis.busy_until(t) for axis in axes))
        for axis in axes:
            axis.status(self.afm.clock.now())
        return []

    def position(self) -> list[Any]:
        """Motor.PosGet: the stage's X and Y sensors and the robot's Z, metres."""
        t = self.afm.clock.now()
        sx, sy = (ax.sensor(t) for ax in self.afm.stage_device.axes)
        return [sx, sy, self.afm.robot_device.axes[2].sensor(t)]

    def stop(self) -> list[Any]:
        """Motor.StopMove: the coarse motors (the robot's Z, the sample stage) stop."""
        t = self.afm.clock.now()
        for axis in (self.afm.robot_device.axes[2], *self.afm.stage_device.axes):
            axis.stop(t)
        return []
