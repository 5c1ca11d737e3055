"""SmarAct MCS controller over its ASCII interface, through pyserial.

The link is opened with :func:`serial.serial_for_url`, so ``/dev/ttyUSB0``,
``socket://host:port`` and ``rfc2217://host:port`` all work. A command is ``:`` + name + channel
+ comma-separated decimals + LF; so is a reply. The driver switches the controller to
synchronous communication first (``:SCM0``); every command then gets exactly one reply, and a
command without data to return is acknowledged with ``:E<channel>,0``.

One lock per link serialises command/reply pairs. Reads that change nothing (position, status,
voltage level, channel count) are retried once after a time-out or a garbled reply; moves are
never retried, because the first one may have been executed.
"""

from __future__ import annotations

import contextlib
import re
import threading
from dataclasses import dataclass
from enum import IntEnum
from types import TracebackType
from typing import Any, Protocol

from hardware.smaract_errors import (
    MCSLinkError,
    MCSProtocolError,
    MCSTimeout,
    controller_error,
)

#: Largest step count of one ``:MST`` command.
MAX_STEPS = 30000
#: Largest step amplitude and fine-mode (scan) level: 12-bit.
MAX_LEVEL = 4095
#: Step frequency range, Hz.
MIN_FREQUENCY, MAX_FREQUENCY = 1, 18500
#: Fine-mode speed range, levels per second.
MIN_SCAN_SPEED, MAX_SCAN_SPEED = 1, 4_095_000_000

_REPLY = re.compile(r"^:([A-Z]+)(-?\d+)?((?:,-?\d+)*)$")


class AxisStatus(IntEnum):
    """Channel status codes of ``:GS``."""

    STOPPED = 0
    STEPPING = 1
    SCANNING = 2
    HOLDING = 3
    TARGETING = 4
    MOVE_DELAY = 5
    CALIBRATING = 6
    FINDING_REFERENCE = 7
    OPENING = 8


class Link(Protocol):
    """What the driver needs of a serial port (``serial.Serial`` has it)."""

    def write(self, data: bytes) -> int | None:
        """Send ``data``; the count written."""
        ...

    def readline(self) -> bytes:
        """The next line received (up to its newline), or what came before the time-out."""
        ...

    def reset_input_buffer(self) -> None:
        """Drop whatever was received and not read."""
        ...

    def close(self) -> None:
        """Close the port."""
        ...


def open_link(url: str, *, timeout: float = 1.0, baudrate: int = 115200) -> Link:
    """Open a pyserial link from a URL or device path; :class:`MCSLinkError` on failure."""
    import serial

    try:
        port: Link = serial.serial_for_url(url, baudrate=baudrate, timeout=timeout)
    except (serial.SerialException, ValueError, OSError) as exc:
        raise MCSLinkError(f"cannot open MCS link {url!r}: {exc}") from exc
    return port


@dataclass(frozen=True)
class Reply:
    """A parsed reply: name, channel (or None) and integer values."""

    name: str
    channel: int | None
    values: tuple[int, ...]


def parse_reply(line: str) -> Reply:
    """Parse ``:NAME<ch>,v1,v2`` (without the LF); :class:`MCSProtocolError` when malformed."""
    m = _REPLY.match(line)
    if not m:
        raise MCSProtocolError(f"garbled reply from the MCS controller: {line!r}")
    name, ch, rest = m.groups()
    values = tuple(int(v) for v in rest.split(",")[1:]) if rest else ()
    return Reply(name, int(ch) if ch is not None else None, values)


class MCSController:
    """One MCS controller on one link.

    Parameters
    ----------
    link : Link
        An open serial-like link (see :func:`open_link`), or anything with the same methods
        (tests pass a transcript).
    name : str
        For messages.
    """

    def __init__(self, link: Link, *, name: str = "mcs") -> None:
        self._link = link
        self._lock = threading.Lock()
        self.name = name
        self._closed = False

    @classmethod
    def open(cls, url: str, *, timeout: float = 1.0, synchronous: bool = True) -> MCSController:
        """Open the link at ``url`` and switch the controller to synchronous communication."""
        ctl = cls(open_link(url, timeout=timeout), name=url)
        if synchronous:
            try:
                ctl.set_synchronous()
            except Exception:
                ctl.close()
                raise
        return ctl

    # -- plumbing ------------------------------------------------------------------------------

    def close(self) -> None:
        """Close the link (once; a link already gone is not an error)."""
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):
                self._link.close()

    def __enter__(self) -> MCSController:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _exchange(self, command: str) -> Reply:
        if self._closed:
            raise MCSLinkError(f"{self.name}: the link is closed")
        try:
            self._link.write(f":{command}\n".encode("ascii"))
            raw = self._link.readline()
        except (OSError, EOFError) as exc:
            raise MCSLinkError(f"{self.name}: link dropped during {command!r}: {exc}") from exc
        except Exception as exc:  # pyserial raises SerialException (an OSError subclass) or
            # its own PortNotOpenError; anything else from the transport is a link failure too
            raise MCSLinkError(f"{self.name}: link failed during {command!r}: {exc}") from exc
        if not raw:
            raise MCSTimeout(f"{self.name}: no reply to {command!r} within the time-out")
        if not raw.endswith(b"\n"):
            raise MCSTimeout(f"{self.name}: incomplete reply to {command!r}: {raw!r}")
        try:
            text = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise MCSProtocolError(f"{self.name}: garbled reply to {command!r}: {raw!r}") from None
        return parse_reply(text)

    def command(self, command: str, *, expect: str = "E", idempotent: bool = False) -> Reply:
        """Send ``command`` and return its reply, which must be named ``expect``.

        An error reply ``:E<ch>,<code != 0>`` raises the typed controller error. Idempotent
        commands are retried once after a time-out or a garbled reply (the stale input is
        discarded first).
        """
        with self._lock:
            attempts = 2 if idempotent else 1
            for attempt in range(attempts):
                try:
                    reply = self._exchange(command)
                except (MCSTimeout, MCSProtocolError):
                    if attempt + 1 == attempts:
                        raise
                    self._discard_input()
                    continue
                if reply.name == "E" and reply.values and reply.values[0] != 0:
                    ch = reply.channel if reply.channel is not None else -1
                    raise controller_error(reply.values[0], ch, command)
                if reply.name != expect:
                    err = MCSProtocolError(
                        f"{self.name}: unexpected reply to {command!r}: {reply.name} "
                        f"(expected {expect})"
                    )
                    if attempt + 1 == attempts:
                        raise err
                    self._discard_input()
                    continue
                return reply
        raise AssertionError("unreachable")  # pragma: no cover

    def _discard_input(self) -> None:
        # a link that cannot flush still gets its retry
        with contextlib.suppress(Exception):
            self._link.reset_input_buffer()

    # -- commands ------------------------------------------------------------------------------

    def set_synchronous(self) -> None:
        """``:SCM0``: one reply per command, moves acknowledged with ``:E<ch>,0``."""
        self.command("SCM0")

    def channel_count(self) -> int:
        """``:GNC`` -> ``:N<count>``."""
        return _one(self.command("GNC", expect="N", idempotent=True), "GNC", channel=True)

    def position(self, channel: int) -> float:
        """``:GP<ch>`` -> position in metres (the controller counts nanometres)."""
        reply = self.command(f"GP{_ch(channel)}", expect="P", idempotent=True)
        return _one(reply, "GP") * 1e-9

    def status(self, channel: int) -> AxisStatus:
        """``:GS<ch>`` -> the channel's :class:`AxisStatus`."""
        code = _one(self.command(f"GS{_ch(channel)}", expect="S", idempotent=True), "GS")
        try:
            return AxisStatus(code)
        except ValueError:
            raise MCSProtocolError(f"{self.name}: unknown status code {code}") from None

    def voltage_level(self, channel: int) -> int:
        """``:GVL<ch>`` -> fine-mode voltage level, 0..4095."""
        return _one(self.command(f"GVL{_ch(channel)}", expect="VL", idempotent=True), "GVL")

    def move_absolute(self, channel: int, position: float, *, hold_ms: int = 0) -> None:
        """``:MPA<ch>,<nm>,<hold ms>``: closed-loop move to ``position`` metres."""
        self.command(f"MPA{_ch(channel)},{_nm(position)},{_hold(hold_ms)}")

    def move_relative(self, channel: int, distance: float, *, hold_ms: int = 0) -> None:
        """``:MPR<ch>,<nm>,<hold ms>``: closed-loop move by ``distance`` metres."""
        self.command(f"MPR{_ch(channel)},{_nm(distance)},{_hold(hold_ms)}")

    def step(self, channel: int, steps: int, *, amplitude: int, frequency: int) -> None:
        """``:MST<ch>,<steps>,<amplitude>,<frequency>``: open-loop stick-slip steps."""
        _check(steps, -MAX_STEPS, MAX_STEPS, "steps")
        _check(amplitude, 0, MAX_LEVEL, "amplitude")
        _check(frequency, MIN_FREQUENCY, MAX_FREQUENCY, "frequency")
        self.command(f"MST{_ch(channel)},{steps},{amplitude},{frequency}")

    def scan_absolute(self, channel: int, level: int, *, speed: int) -> None:
        """``:MSCA<ch>,<level>,<speed>``: fine mode to voltage ``level`` at ``speed`` levels/s."""
        _check(level, 0, MAX_LEVEL, "level")
        _check(speed, MIN_SCAN_SPEED, MAX_SCAN_SPEED, "speed")
        self.command(f"MSCA{_ch(channel)},{level},{speed}")

    def scan_relative(self, channel: int, levels: int, *, speed: int) -> None:
        """``:MSCR<ch>,<±levels>,<speed>``: fine mode by ``levels``."""
        _check(levels, -MAX_LEVEL, MAX_LEVEL, "levels")
        _check(speed, MIN_SCAN_SPEED, MAX_SCAN_SPEED, "speed")
        self.command(f"MSCR{_ch(channel)},{levels},{speed}")

    def stop(self, channel: int) -> None:
        """``:S<ch>``: stop the channel at once."""
        self.command(f"S{_ch(channel)}")

    def set_watchdog(self, milliseconds: int) -> None:
        """``:K<ms>``: the controller stops every channel when no command arrives for this
        long (0 disables)."""
        _check(milliseconds, 0, 2**31 - 1, "milliseconds")
        self.command(f"K{milliseconds}")

    def set_position_limit(self, channel: int, low: float, high: float) -> None:
        """``:SPL<ch>,<min nm>,<max nm>``: soft range limit (both 0 removes it)."""
        if high < low:
            raise ValueError(f"position limit high {high} is below low {low}")
        self.command(f"SPL{_ch(channel)},{_nm(low)},{_nm(high)}")

    def position_limit(self, channel: int) -> tuple[float, float]:
        """``:GPL<ch>`` -> ``:PL<ch>,<min nm>,<max nm>`` in metres."""
        reply = self.command(f"GPL{_ch(channel)}", expect="PL", idempotent=True)
        if len(reply.values) != 2:
            raise MCSProtocolError(f"{self.name}: bad GPL reply {reply}")
        return reply.values[0] * 1e-9, reply.values[1] * 1e-9


def _ch(channel: int) -> int:
    if not isinstance(channel, int) or channel < 0:
        raise ValueError(f"channel must be a non-negative integer, got {channel!r}")
    return channel


def _nm(metres: float) -> int:
    value = round(metres * 1e9)
    _check(value, -(2**31), 2**31 - 1, "position (nm)")
    return value


def _hold(ms: int) -> int:
    _check(ms, 0, 60000, "hold time (ms)")
    return ms


def _check(value: Any, low: int, high: int, what: str) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise ValueError(f"{what} must be an integer in [{low}, {high}], got {value!r}")


def _one(reply: Reply, command: str, *, channel: bool = False) -> int:
    if channel and reply.channel is not None and not reply.values:
        return reply.channel  # ``:N<count>`` carries its value where a channel would be
    if len(reply.values) != 1:
        raise MCSProtocolError(f"bad reply to {command}: {reply}")
    return reply.values[0]
