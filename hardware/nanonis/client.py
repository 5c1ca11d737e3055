"""A Nanonis controller over TCP: one command, one response, typed errors.

One lock per link serialises request/response pairs. A link that dropped, timed out or
answered out of step is closed: its byte stream can no longer be trusted, and the next command
opens a new connection. Commands that are safe to repeat (reads, and the safety commands:
withdraw, Z controller off, scan stop, motor stop) are retried once on a new connection;
anything that may have moved the instrument is never retried.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any, Protocol

from hardware.nanonis import wire
from hardware.nanonis.errors import (
    NanonisCommandError,
    NanonisError,
    NanonisLinkError,
    NanonisProtocolError,
    NanonisTimeout,
)


class Stream(Protocol):
    """What the client needs of a connection (a ``socket.socket`` has it)."""

    def sendall(self, data: bytes, /) -> None: ...

    def recv(self, size: int, /) -> bytes: ...

    def settimeout(self, value: float | None, /) -> None: ...

    def close(self) -> None: ...


#: Scan.Action codes
SCAN_START, SCAN_STOP, SCAN_PAUSE, SCAN_RESUME = 0, 1, 2, 3
#: Motor.StartMove directions
MOTOR_DIRECTIONS = {"X+": 0, "X-": 1, "Y+": 2, "Y-": 3, "Z+": 4, "Z-": 5}


class NanonisClient:
    """One Nanonis TCP programming interface.

    Parameters
    ----------
    connect : callable
        Opens a new connection (a socket, or a transcript in tests); called at the first
        command and again after a link was closed by a failure.
    name : str
        For messages (``host:port``).
    timeout : float
        Seconds to wait for a response (a command may give its own).
    """

    def __init__(self, connect: Callable[[], Stream], *, name: str, timeout: float = 5.0) -> None:
        self._connect = connect
        self.name = name
        self.timeout = timeout
        self._stream: Stream | None = None
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, host: str, port: int, *, timeout: float = 5.0) -> NanonisClient:
        """Connect to ``host:port`` now (so a wrong address fails at start-up)."""

        def connect() -> Stream:
            try:
                return socket.create_connection((host, port), timeout=timeout)
            except OSError as exc:
                raise NanonisLinkError(f"cannot reach Nanonis at {host}:{port}: {exc}") from exc

        client = cls(connect, name=f"{host}:{port}", timeout=timeout)
        with client._lock:
            client._stream = connect()
        return client

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._drop()

    def __enter__(self) -> NanonisClient:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- plumbing ---------------------------------------------------------------------------

    def _drop(self) -> None:
        if self._stream is not None:
            with contextlib.suppress(OSError):
                self._stream.close()
            self._stream = None

    def _recv_exact(self, stream: Stream, n: int, command: str) -> bytes:
        chunks, got = [], 0
        while got < n:
            chunk = stream.recv(min(n - got, 1 << 20))
            if not chunk:
                raise NanonisLinkError(f"{self.name}: link closed during {command}")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def _exchange(self, command: str, message: bytes, timeout: float) -> bytes:
        if self._closed:
            raise NanonisLinkError(f"{self.name}: the link is closed")
        if self._stream is None:
            self._stream = self._connect()
        stream = self._stream
        try:
            stream.settimeout(timeout)
            stream.sendall(message)
            header = wire.decode_header(self._recv_exact(stream, wire.HEADER_SIZE, command))
            body = self._recv_exact(stream, header.body_size, command)
        except TimeoutError:
            self._drop()
            raise NanonisTimeout(
                f"{self.name}: no response to {command} within {timeout:g} s"
            ) from None
        except NanonisError:
            self._drop()
            raise
        except OSError as exc:
            self._drop()
            raise NanonisLinkError(f"{self.name}: link failed during {command}: {exc}") from exc
        if header.command != command:
            self._drop()
            raise NanonisProtocolError(
                f"{self.name}: response to {header.command!r} while waiting for {command!r}"
            )
        return body

    def call(
        self,
        command: str,
        arg_types: Sequence[str] = (),
        args: Sequence[Any] = (),
        reply_types: Sequence[str] = (),
        *,
        repeatable: bool = False,
        timeout: float | None = None,
    ) -> list[Any]:
        """Send ``command`` with ``args``; return its values (types as :mod:`wire` names them).

        A response whose error block is set raises :class:`NanonisCommandError`. A
        ``repeatable`` command is sent once more on a new connection after a dropped link,
        a time-out or a garbled response.
        """
        message = wire.request(command, arg_types, args)
        wait = self.timeout if timeout is None else timeout
        with self._lock:
            for attempt in range(2 if repeatable else 1):
                try:
                    body = self._exchange(command, message, wait)
                    values, status, description = wire.decode_response(
                        reply_types, body, command=command
                    )
                except (NanonisLinkError, NanonisTimeout, NanonisProtocolError):
                    self._drop()
                    if attempt == 0 and repeatable:
                        continue
                    raise
                if status != 0:
                    raise NanonisCommandError(command, status, description)
                return values
        raise AssertionError("unreachable")  # pragma: no cover

    # -- PLL (oscillation control) ----------------------------------------------------------

    def frequency_shift(self, modulator: int = 1) -> float:
        """``PLL.FreqShiftGet``: Δf, Hz."""
        return float(self.call("PLL.FreqShiftGet", "i", [modulator], "f", repeatable=True)[0])

    def frequency_range(self, modulator: int = 1) -> float:
        """``PLL.FreqRangeGet``: the PLL's frequency range, Hz (beyond it, lock is lost)."""
        return float(self.call("PLL.FreqRangeGet", "i", [modulator], "f", repeatable=True)[0])

    def amplitude_setpoint(self, modulator: int = 1) -> float:
        """``PLL.AmpCtrlSetpntGet``: the amplitude controller's set-point, metres."""
        values = self.call("PLL.AmpCtrlSetpntGet", "i", [modulator], "f", repeatable=True)
        return float(values[0])

    # -- signals ----------------------------------------------------------------------------

    def signal_names(self) -> list[str]:
        """``Signals.NamesGet``: the names of all signals, by index."""
        names: list[str] = self.call("Signals.NamesGet", (), (), ["as"], repeatable=True)[0]
        return names

    def signal_value(self, index: int, *, newest: bool = False) -> float:
        """``Signals.ValGet``: the present value of signal ``index``."""
        values = self.call("Signals.ValGet", "iI", [index, int(newest)], "f", repeatable=True)
        return float(values[0])

    # -- Z controller -----------------------------------------------------------------------

    def z_controller(self, on: bool) -> None:
        """``ZCtrl.OnOffSet``; switching off is repeatable, switching on is not."""
        self.call("ZCtrl.OnOffSet", "I", [int(on)], repeatable=not on)

    def z_controller_on(self) -> bool:
        """``ZCtrl.OnOffGet``: the real-time controller's state."""
        return bool(self.call("ZCtrl.OnOffGet", (), (), "I", repeatable=True)[0])

    def set_setpoint(self, value: float) -> None:
        """``ZCtrl.SetpntSet``: in the feedback signal's unit (Hz on Δf)."""
        self.call("ZCtrl.SetpntSet", "f", [value], repeatable=True)

    def setpoint(self) -> float:
        """``ZCtrl.SetpntGet``."""
        return float(self.call("ZCtrl.SetpntGet", (), (), "f", repeatable=True)[0])

    def z_position(self) -> float:
        """``ZCtrl.ZPosGet``: the Z piezo, metres (high limit = withdrawn)."""
        return float(self.call("ZCtrl.ZPosGet", (), (), "f", repeatable=True)[0])

    def set_z_position(self, z: float) -> None:
        """``ZCtrl.ZPosSet`` (the controller must be off)."""
        self.call("ZCtrl.ZPosSet", "f", [z])

    def z_limits(self) -> tuple[float, float]:
        """``ZCtrl.LimitsGet``: (high, low) metres."""
        high, low = self.call("ZCtrl.LimitsGet", (), (), "ff", repeatable=True)
        return float(high), float(low)

    def withdraw(self, *, wait: bool = True, timeout_ms: int = 5000) -> None:
        """``ZCtrl.Withdraw``: Z controller off, tip to the high limit."""
        self.call(
            "ZCtrl.Withdraw",
            "Ii",
            [int(wait), timeout_ms],
            repeatable=True,
            timeout=self.timeout + max(0, timeout_ms) / 1000,
        )

    # -- piezos and follow-me ---------------------------------------------------------------

    def piezo_range(self) -> tuple[float, float, float]:
        """``Piezo.RangeGet``: X, Y, Z ranges, metres."""
        x, y, z = self.call("Piezo.RangeGet", (), (), "fff", repeatable=True)
        return float(x), float(y), float(z)

    def tip_xy(self) -> tuple[float, float]:
        """``FolMe.XYPosGet``: the tip's X, Y, metres (0 at the middle of the range)."""
        x, y = self.call("FolMe.XYPosGet", "I", [0], "dd", repeatable=True)
        return float(x), float(y)

    def move_tip(self, x: float, y: float, *, wait: bool = True) -> None:
        """``FolMe.XYPosSet``."""
        self.call("FolMe.XYPosSet", "ddI", [x, y, int(wait)], timeout=4 * self.timeout)

    def set_tip_speed(self, speed: float) -> None:
        """``FolMe.SpeedSet`` with the custom speed in use, m/s."""
        self.call("FolMe.SpeedSet", "fI", [speed, 1], repeatable=True)

    def stop_tip(self) -> None:
        """``FolMe.Stop``."""
        self.call("FolMe.Stop", repeatable=True)

    # -- scan -------------------------------------------------------------------------------

    def set_frame(
        self, centre: tuple[float, float], size: tuple[float, float], angle: float
    ) -> None:
        """``Scan.FrameSet``: centre and size in metres, angle in degrees (clockwise)."""
        self.call("Scan.FrameSet", "fffff", [*centre, *size, angle], repeatable=True)

    def frame(self) -> tuple[float, float, float, float, float]:
        """``Scan.FrameGet``: centre x, y, width, height (m), angle (deg)."""
        cx, cy, w, h, a = self.call("Scan.FrameGet", (), (), "fffff", repeatable=True)
        return float(cx), float(cy), float(w), float(h), float(a)

    def set_buffer(self, channels: Sequence[int], pixels: int, lines: int) -> None:
        """``Scan.BufferSet``: recorded channels (signal slots), pixels per line, lines."""
        self.call(
            "Scan.BufferSet", ["ai", "i", "i"], [list(channels), pixels, lines], repeatable=True
        )

    def buffer(self) -> tuple[list[int], int, int]:
        """``Scan.BufferGet``: channels, pixels per line (as coerced), lines."""
        channels, pixels, lines = self.call(
            "Scan.BufferGet", (), (), ["ai", "i", "i"], repeatable=True
        )
        return list(channels), int(pixels), int(lines)

    def set_speed(self, forward_time: float, backward_time: float, width: float) -> None:
        """``Scan.SpeedSet`` keeping the time per line: seconds per forward and backward
        line over a frame ``width`` metres wide."""
        ratio = forward_time / backward_time
        self.call(
            "Scan.SpeedSet",
            "ffffHf",
            [width / forward_time, width / backward_time, forward_time, backward_time, 2, ratio],
            repeatable=True,
        )

    def speed(self) -> tuple[float, float, float, float, int, float]:
        """``Scan.SpeedGet``: speeds (m/s), times per line (s), what is kept, ratio."""
        v = self.call("Scan.SpeedGet", (), (), "ffffHf", repeatable=True)
        return float(v[0]), float(v[1]), float(v[2]), float(v[3]), int(v[4]), float(v[5])

    def scan_action(self, action: int, *, up: bool = True) -> None:
        """``Scan.Action``: start, stop, pause, resume (stop is repeatable)."""
        self.call("Scan.Action", "HI", [action, int(up)], repeatable=action == SCAN_STOP)

    def scanning(self) -> bool:
        """``Scan.StatusGet``."""
        return bool(self.call("Scan.StatusGet", (), (), "I", repeatable=True)[0])

    def wait_end_of_scan(self, timeout: float) -> bool:
        """``Scan.WaitEndOfScan`` for up to ``timeout`` s; True when the frame ended."""
        ms = max(1, round(timeout * 1000))
        timed_out, _path = self.call(
            "Scan.WaitEndOfScan", "i", [ms], ["I", "s"], timeout=self.timeout + timeout
        )
        return not timed_out

    def grab_frame(self, channel: int, *, forward: bool = True) -> tuple[str, Any, bool]:
        """``Scan.FrameDataGrab``: channel name, data (rows, columns), whether scanned up."""
        name, data, up = self.call(
            "Scan.FrameDataGrab",
            "II",
            [channel, int(forward)],
            ["s", "2f", "I"],
            repeatable=True,
            timeout=4 * self.timeout,
        )
        return str(name), data, bool(up)

    # -- approach and coarse motors ---------------------------------------------------------

    def auto_approach(self, on: bool) -> None:
        """``AutoApproach.OnOffSet``."""
        self.call("AutoApproach.OnOffSet", "H", [int(on)], repeatable=not on)

    def auto_approach_running(self) -> bool:
        """``AutoApproach.OnOffGet``."""
        return bool(self.call("AutoApproach.OnOffGet", (), (), "H", repeatable=True)[0])

    def motor_move(self, direction: str, steps: int, *, group: int = 0, wait: bool = True) -> None:
        """``Motor.StartMove`` ``steps`` (0..65535) towards ``direction`` (``X+`` .. ``Z-``)."""
        if direction not in MOTOR_DIRECTIONS or not 0 <= steps <= 0xFFFF:
            raise ValueError(f"motor move {direction!r} x {steps}: use X+..Z- and 0..65535")
        self.call(
            "Motor.StartMove",
            "IHII",
            [MOTOR_DIRECTIONS[direction], steps, group, int(wait)],
            timeout=self.timeout + steps / 100,
        )

    def motor_move_to(
        self, target: tuple[float, float, float], *, group: int = 0, wait: bool = True
    ) -> None:
        """``Motor.StartClosedLoop`` to an absolute target, metres."""
        self.call(
            "Motor.StartClosedLoop",
            "IdddII",
            [1, *target, int(wait), group],
            timeout=6 * self.timeout,
        )

    def motor_position(self, *, group: int = 0) -> tuple[float, float, float]:
        """``Motor.PosGet``: X, Y, Z of the coarse motors, metres."""
        x, y, z = self.call("Motor.PosGet", "II", [group, 500], "ddd", repeatable=True)
        return float(x), float(y), float(z)

    def motor_stop(self) -> None:
        """``Motor.StopMove``."""
        self.call("Motor.StopMove", repeatable=True)
