"""The simulated Nanonis controller: its TCP commands on top of the simulated world.

:meth:`NanonisController.handle` takes one request (command name and body bytes) and returns
the whole response message, error block included, as the real controller's TCP interface
does: an unknown command, arguments of the wrong size or a value out of range get a response
whose error block says what is wrong. What the commands act on is the physics of
:class:`~hardware.sim.instrument.SimulatedAFM`:

* the PLL reads the Akiyama probe's Δf(d) (``PLL.*``, ``Signals.ValGet``);
* the Z controller is the world's finite-bandwidth force loop on the probe robot's Z piezo;
  Z is reported as Nanonis does, ``high limit - extension`` (withdrawn = high limit);
* the scan generator rasters frames over the robot's X and Y piezos in a background task
  (:mod:`hardware.sim.nanonis_scan`), forward and backward;
* the auto-approach runs the woodpecker landing on the robot's Z (coarse steps between fine
  approaches) and ends with the loop engaged at the set-point;
* the coarse motor module steps the robot's Z (``Z-`` approaches) and moves the sample
  stage's X and Y (open loop, or closed loop on its sensors: :mod:`hardware.sim.nanonis_motor`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hardware.errors import ProcedureError
from hardware.nanonis import wire
from hardware.nanonis.errors import NanonisProtocolError
from hardware.procedures import LandingConfig, land
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_motor import MotorModule
from hardware.sim.nanonis_scan import Frame, FrameScan, ramp_xy

#: The signal slot the scan buffer records Z from (as on many installations).
Z_SLOT = 14
#: Signals by index (Signals.NamesGet, Signals.ValGet): the ones the simulator has.
SIGNALS = ("Current (A)", "Bias (V)", "Z (m)", "OC M1 Freq. Shift (Hz)", "OC M1 Amplitude (m)")


class Refused(Exception):
    """A command the controller answers with its error block set."""


@dataclass
class _Command:
    args: str | tuple[str, ...]
    replies: str | tuple[str, ...]
    run: Callable[[list[Any]], list[Any]]


class NanonisController:
    """The controller's state (set-point, frame, buffer, speeds) over the world ``afm``."""

    def __init__(self, afm: SimulatedAFM) -> None:
        self.afm = afm
        self.world = threading.RLock()
        z = afm.robot_device.axes[2]
        self.z_range = z.params.fine_range
        self.xy_range = tuple(a.params.fine_range for a in afm.robot_device.axes[:2])
        self.setpoint = 10.0
        self.frame = Frame()
        self.channels: list[int] = [Z_SLOT]
        self.pixels, self.lines = 256, 256
        self.times = (1.0, 1.0)  # forward, backward seconds per line
        self.tip_speed = 1e-6
        self._scan: FrameScan | None = None
        self._task: threading.Thread | None = None
        self._task_kind = ""
        self._stop = threading.Event()
        self._idle = threading.Event()
        self._idle.set()
        self.approach_error = ""
        #: faults of the physics waiting for a frame's line: (what it does, after how many)
        self.pending: list[tuple[Callable[[], None], int]] = []
        c = _Command
        motor = self.motor = MotorModule(afm)
        self.commands: dict[str, _Command] = {
            "PLL.FreqShiftGet": c("i", "f", lambda a: [self._df()]),
            "PLL.FreqRangeGet": c("i", "f", lambda a: [afm.probe.pll_range]),
            "PLL.AmpCtrlSetpntGet": c("i", "f", lambda a: [afm.probe.amplitude]),
            "Signals.NamesGet": c("", ("as",), lambda a: [list(SIGNALS)]),
            "Signals.ValGet": c("iI", "f", self._signal),
            "ZCtrl.OnOffSet": c("I", "", self._z_on_off),
            "ZCtrl.OnOffGet": c("", "I", lambda a: [int(afm.engaged())]),
            "ZCtrl.StatusGet": c("", "H", lambda a: [2 if afm.engaged() else 1]),
            "ZCtrl.SetpntSet": c("f", "", self._set_setpoint),
            "ZCtrl.SetpntGet": c("", "f", lambda a: [self.setpoint]),
            "ZCtrl.ZPosGet": c("", "f", lambda a: [self._z()]),
            "ZCtrl.ZPosSet": c("f", "", self._set_z),
            "ZCtrl.LimitsGet": c("", "ff", lambda a: [self.z_range / 2, -self.z_range / 2]),
            "ZCtrl.Withdraw": c("Ii", "", self._withdraw),
            "Piezo.RangeGet": c("", "fff", lambda a: [*self.xy_range, self.z_range]),
            "FolMe.XYPosGet": c("I", "dd", lambda a: list(self._tip_xy())),
            "FolMe.XYPosSet": c("ddI", "", self._move_tip),
            "FolMe.SpeedSet": c("fI", "", self._set_tip_speed),
            "FolMe.Stop": c("", "", lambda a: self._stop_tip()),
            "Scan.FrameSet": c("fffff", "", self._set_frame),
            "Scan.FrameGet": c("", "fffff", lambda a: self._frame_values()),
            "Scan.BufferSet": c(("ai", "i", "i"), "", self._set_buffer),
            "Scan.BufferGet": c(
                "", ("ai", "i", "i"), lambda a: [self.channels, self.pixels, self.lines]
            ),
            "Scan.SpeedSet": c("ffffHf", "", self._set_speed),
            "Scan.SpeedGet": c("", "ffffHf", lambda a: self._speed_values()),
            "Scan.Action": c("HI", "", self._scan_action),
            "Scan.StatusGet": c("", "I", lambda a: [int(self._busy("scan"))]),
            "Scan.WaitEndOfScan": c("i", ("I", "s"), self._wait_end),
            "Scan.FrameDataGrab": c("II", ("s", "2f", "I"), self._grab),
            "AutoApproach.OnOffSet": c("H", "", self._approach),
            "AutoApproach.OnOffGet": c("", "H", lambda a: [int(self._busy("approach"))]),
            "Motor.StartMove": c("IHII", "", motor.start_move),
            "Motor.StartClosedLoop": c("IdddII", "", motor.closed_loop),
            "Motor.PosGet": c("II", "ddd", lambda a: motor.position()),
            "Motor.StopMove": c("", "", lambda a: motor.stop()),
        }

    # -- the request/response cycle ---------------------------------------------------------

    def handle(self, command: str, body: bytes) -> bytes:
        """The response message to ``command`` with argument bytes ``body``."""
        spec = self.commands.get(command)
        if spec is None:
            return wire.response(
                command,
                status=1,
                description=f"unknown command {command!r}: the simulated "
                f"controller knows {len(self.commands)} commands",
            )
        try:
            args, used = wire.decode(spec.args, body, what=command)
            if used != len(body):
                raise Refused(f"{len(body) - used} bytes beyond the arguments of {command}")
            if command == "Scan.WaitEndOfScan":  # waits without holding the world
                values = spec.run(args)
            else:
                with self.world:
                    self.afm.clock.advance(0.001)  # time moves on demand (sim.clock)
                    values = spec.run(args)
            return wire.response(command, spec.replies, values)
        except (Refused, NanonisProtocolError, ProcedureError, ValueError) as exc:
            return self.refusal(command, str(exc))

    def refusal(self, command: str, description: str, *, status: int = 1) -> bytes:
        """A response refusing ``command``: its return values as placeholders (the layout
        stays the command's), then the error block with ``status`` and ``description``."""
        spec = self.commands.get(command)
        types = spec.replies if spec is not None else ()
        return wire.response(
            command, types, wire.placeholders(types), status=status, description=description
        )

    def close(self) -> None:
        with self.world:
            self._halt()
        if self._task is not None:
            self._task.join(10.0)

    # -- background tasks: one frame scan or one approach at a time ---------------------------
    #
    # Commands run holding the world lock; a frame scan takes it line by line, so commands
    # interleave between lines. Halting a task under the lock only raises its stop flag: the
    # task cannot be inside a line then, and it leaves at its next one without touching the
    # world again.

    def _busy(self, kind: str) -> bool:
        return not self._idle.is_set() and not self._stop.is_set() and self._task_kind == kind

    def _start(self, kind: str, work: Callable[[threading.Event], None]) -> None:
        if not self._idle.is_set():
            raise Refused(f"the {self._task_kind} is running: stop it first")
        stop, idle = threading.Event(), threading.Event()
        self._stop, self._idle, self._task_kind = stop, idle, kind

        def body() -> None:
            try:
                work(stop)
            finally:
                idle.set()

        self._task = threading.Thread(target=body, name=f"nanonis-{kind}", daemon=True)
        self._task.start()

    def _halt(self) -> None:
        self._stop.set()

    # -- PLL, signals -----------------------------------------------------------------------

    def _df(self) -> float:
        return float(self.afm.frequency_shift())

    def _signal(self, a: list[Any]) -> list[Any]:
        index = int(a[0])
        if not 0 <= index < len(SIGNALS):
            raise Refused(f"signal index {index} is not in 0..{len(SIGNALS) - 1}")
        name = SIGNALS[index]
        if name.startswith("Z"):
            return [self._z()]
        if "Freq. Shift" in name:
            return [self._df()]
        if "Amplitude" in name:
            return [self.afm.amplitude()]
        return [0.0]

    # -- Z controller -----------------------------------------------------------------------

    def _z(self) -> float:
        afm = self.afm
        if self._idle.is_set():
            afm.track()
        return self.z_range / 2 - afm.robot_device.axes[2].extension(afm.clock.now())

    def _z_on_off(self, a: list[Any]) -> list[Any]:
        if a[0] == 1:
            if self.afm.pll_lost or self.afm.crashed:
                raise Refused("the Δf signal is not valid (PLL unlocked): Z controller stays off")
            self.afm.engage(self.setpoint)
        elif a[0] == 0:
            self.afm.hold()
        else:
            raise Refused(f"Z controller status must be 0 or 1, got {a[0]}")
        return []

    def _set_setpoint(self, a: list[Any]) -> list[Any]:
        value = float(a[0])
        try:
            self.afm.probe.distance_at(value)
        except ValueError:
            raise Refused(
                f"set-point {value:g} Hz is outside the Δf the loop can regulate on"
            ) from None
        self.setpoint = value
        if self.afm.engaged():
            self.afm.engage(value)
        return []

    def _set_z(self, a: list[Any]) -> list[Any]:
        if self.afm.engaged():
            raise Refused("switch the Z controller off before setting Z")
        ext = self.z_range / 2 - float(a[0])
        if not 0 <= ext <= self.z_range:
            raise Refused(f"Z {a[0]:g} m is outside the limits ±{self.z_range / 2:g} m")
        self.afm.robot_device.axes[2].drive_extension(ext, self.afm.clock.now())
        return []

    def _withdraw(self, a: list[Any]) -> list[Any]:
        self._halt()
        self.afm.withdraw()
        return []

    # -- piezos, follow-me ------------------------------------------------------------------

    def _tip_xy(self) -> tuple[float, float]:
        t = self.afm.clock.now()
        x, y = (
            ax.extension(t) - r / 2
            for ax, r in zip(self.afm.robot_device.axes[:2], self.xy_range, strict=True)
        )
        return x, y

    def _move_tip(self, a: list[Any]) -> list[Any]:
        if not self._idle.is_set():
            raise Refused(f"the {self._task_kind} is running: the tip cannot follow-me")
        target = (float(a[0]), float(a[1]))
        if abs(target[0]) > self.xy_range[0] / 2 or abs(target[1]) > self.xy_range[1] / 2:
            raise Refused(f"tip position {target} is outside the scan range")
        x0, y0 = self._tip_xy()
        distance = float(np.hypot(target[0] - x0, target[1] - y0))
        ramp_xy(self.afm, target, duration=max(distance / self.tip_speed, 1e-3))
        t = self.afm.clock.now()
        self.afm.clock.advance_to(max(ax.busy_until(t) for ax in self.afm.robot_device.axes[:2]))
        self.afm.track()
        return []

    def _set_tip_speed(self, a: list[Any]) -> list[Any]:
        if not float(a[0]) > 0:
            raise Refused(f"speed must be positive, got {a[0]:g} m/s")
        self.tip_speed = float(a[0])
        return []

    def _stop_tip(self) -> list[Any]:
        """FolMe.Stop: the scan piezos stop where they are (a running frame with them)."""
        t = self.afm.clock.now()
        for axis in self.afm.robot_device.axes[:2]:
            axis.stop(t)
        self._halt()
        return []

    # -- scan -------------------------------------------------------------------------------

    def _set_frame(self, a: list[Any]) -> list[Any]:
        cx, cy, w, h, angle = (float(v) for v in a)
        frame = Frame((cx, cy), (w, h), angle)
        if not (w > 0 and h > 0):
            raise Refused(f"frame size must be positive, got {w:g} x {h:g} m")
        if not frame.inside((self.xy_range[0] / 2, self.xy_range[1] / 2)):
            raise Refused(
                f"frame {w:g} x {h:g} m at ({cx:g}, {cy:g}), {angle:g}° leaves the scan range "
                f"{self.xy_range[0]:g} x {self.xy_range[1]:g} m"
            )
        self.frame = frame
        return []

    def _frame_values(self) -> list[Any]:
        f = self.frame
        return [*f.centre, *f.size, f.angle]

    def _set_buffer(self, a: list[Any]) -> list[Any]:
        channels, pixels, lines = list(a[0]), int(a[1]), int(a[2])
        if not channels or any(ch != Z_SLOT for ch in channels):
            raise Refused(
                f"the simulated controller records Z only (slot {Z_SLOT}), got channels {channels}"
            )
        if not (1 <= pixels <= 4096 and 1 <= lines <= 4096):
            raise Refused(f"pixels and lines must be in 1..4096, got {pixels} x {lines}")
        # the scan module sends data in packages of 16 pixels: pixels per line snap to them
        self.channels, self.pixels, self.lines = channels, max(16, 16 * round(pixels / 16)), lines
        return []

    def _set_speed(self, a: list[Any]) -> list[Any]:
        v_fwd, v_bwd, t_fwd, t_bwd, keep, _ratio = a
        w = self.frame.size[0]
        if keep == 1:  # keep the linear speeds
            if not (v_fwd > 0 and v_bwd > 0):
                raise Refused("linear speeds must be positive")
            t_fwd, t_bwd = w / v_fwd, w / v_bwd
        elif not (t_fwd > 0 and t_bwd > 0):
            raise Refused("times per line must be positive")
        self.times = (float(t_fwd), float(t_bwd))
        return []

    def _speed_values(self) -> list[Any]:
        w = self.frame.size[0]
        t_fwd, t_bwd = self.times
        return [w / t_fwd, w / t_bwd, t_fwd, t_bwd, 1, t_fwd / t_bwd]

    def _scan_action(self, a: list[Any]) -> list[Any]:
        action, up = int(a[0]), bool(a[1])
        if action == 0:
            if not self.afm.engaged():
                raise Refused("the Z controller is off: land before scanning")
            scan = FrameScan(self.afm, self.frame, (self.pixels, self.lines), self.times, up=up)
            self._scan = scan
            self._start("scan", lambda stop: scan.run(self.world, stop, self._after_line))
        elif action == 1:
            if self._busy("scan"):
                self._halt()
        elif action not in (2, 3, 4, 5, 6):
            raise Refused(f"scan action {action} is not in 0..6")
        return []

    def _after_line(self, k: int) -> None:
        due = [fault for fault, lines in self.pending if k + 1 >= lines]
        self.pending = [(fault, lines) for fault, lines in self.pending if k + 1 < lines]
        for fault in due:
            fault()

    def _wait_end(self, a: list[Any]) -> list[Any]:
        timeout = int(a[0])
        idle = self._idle
        ended = idle.wait(None if timeout < 0 else timeout / 1000)
        return [int(not ended), ""]

    def _grab(self, a: list[Any]) -> list[Any]:
        channel, forward = int(a[0]), bool(a[1])
        if channel not in self.channels:
            raise Refused(f"channel {channel} is not recorded (buffer: {self.channels})")
        if self._scan is None:
            raise Refused("no frame has been scanned yet")
        data = self._scan.data
        return ["Z (m)", data.forward if forward else data.backward, int(data.up)]

    # -- approach ---------------------------------------------------------------------------

    def _approach(self, a: list[Any]) -> list[Any]:
        if a[0] == 0:
            if self._busy("approach"):
                self._halt()
            return []
        afm = self.afm
        config = LandingConfig(setpoint=self.setpoint)

        def work(stop: threading.Event) -> None:
            with self.world:
                try:
                    land(afm.robot_z, afm, afm, config)
                    self.approach_error = ""
                except ProcedureError as exc:
                    self.approach_error = str(exc)
                    afm.withdraw()

        self._start("approach", work)
        return []
