"""The simulated MCS controller: the ASCII protocol on top of simulated channels.

:meth:`MCSDevice.handle` takes one command line and the simulated time and returns the reply
line (or None where the real controller stays silent: movement commands in asynchronous mode).
It answers bad commands, bad channels and out-of-range values with the real controller's error
replies, and implements the keep-alive watchdog.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hardware.sim.mcs_channel import ChannelParams, MCSChannel
from hardware.smaract_mcs import (
    MAX_FREQUENCY,
    MAX_LEVEL,
    MAX_SCAN_SPEED,
    MAX_STEPS,
    MIN_FREQUENCY,
    MIN_SCAN_SPEED,
)

# error codes of the ASCII interface (see hardware.smaract_errors.ERROR_MEANINGS)
SYNTAX, INVALID_COMMAND, TOO_FEW, TOO_MANY, INVALID_PARAMETER, WRONG_MODE = 1, 2, 5, 6, 7, 8
NO_SENSOR, END_STOP, RANGE_LIMIT = 129, 142, 147

_LINE = re.compile(r"^:([A-Z]+?)(-?\d+(?:,-?\d+)*)?$")


class _Reject(Exception):
    def __init__(self, code: int, channel: int = -1) -> None:
        super().__init__(code)
        self.code, self.channel = code, channel


@dataclass
class MCSDevice:
    """A controller with ``channels`` positioners; ``seed`` makes its physics reproducible."""

    channels: int = 3
    params: ChannelParams = field(default_factory=ChannelParams)
    seed: int = 0
    synchronous: bool = False
    watchdog_ms: int = 0
    last_command: float = 0.0
    axes: list[MCSChannel] = field(init=False)

    def __post_init__(self) -> None:
        if not 1 <= self.channels <= 64:
            raise ValueError(f"an MCS controller has 1 to 64 channels, got {self.channels}")
        rng = np.random.default_rng(self.seed)
        self.axes = [
            MCSChannel(params=self.params, rng=np.random.default_rng(rng.integers(2**32)))
            for _ in range(self.channels)
        ]

    # -- protocol --------------------------------------------------------------------------------

    def handle(self, line: str, t: float) -> str | None:
        """Reply to one command line (without LF) at simulated time ``t``."""
        self._check_watchdog(t)
        self.last_command = t
        try:
            return self._dispatch(line.strip(), t)
        except _Reject as rej:
            return f":E{rej.channel},{rej.code}"

    def busy_until(self, t: float) -> float:
        """When the last running motion of any channel ends (a read waits for it)."""
        return max(axis.busy_until(t) for axis in self.axes)

    def _check_watchdog(self, t: float) -> None:
        if self.watchdog_ms and (t - self.last_command) * 1000.0 > self.watchdog_ms:
            for axis in self.axes:
                axis.stop(t)

    def _dispatch(self, line: str, t: float) -> str | None:
        if not line.startswith(":"):
            raise _Reject(SYNTAX)
        m = _LINE.match(line)
        if not m:
            raise _Reject(SYNTAX)
        text = line[1:]
        for name, (n_args, handler) in _COMMANDS:
            if text.startswith(name):
                rest = text[len(name) :]
                try:
                    args = [int(v) for v in rest.split(",")] if rest else []
                except ValueError:
                    raise _Reject(SYNTAX) from None
                if len(args) < n_args:
                    raise _Reject(TOO_FEW)
                if len(args) > n_args:
                    raise _Reject(TOO_MANY)
                return handler(self, args, t)
        raise _Reject(INVALID_COMMAND)

    def _axis(self, ch: int) -> MCSChannel:
        if not 0 <= ch < len(self.axes):
            raise _Reject(INVALID_PARAMETER)
        return self.axes[ch]

    def _ack(self, ch: int) -> str | None:
        return f":E{ch},0" if self.synchronous else None

    # -- handlers (args are already integers) ----------------------------------------------------

    def _scm(self, a: list[int], t: float) -> str:
        if a[0] not in (0, 1):
            raise _Reject(INVALID_PARAMETER)
        self.synchronous = a[0] == 0
        return ":E-1,0"

    def _gnc(self, a: list[int], t: float) -> str:
        return f":N{len(self.axes)}"

    def _gp(self, a: list[int], t: float) -> str:
        axis = self._axis(a[0])
        if not axis.params.has_sensor:
            raise _Reject(NO_SENSOR, a[0])
        return f":P{a[0]},{round(axis.sensor(t) * 1e9)}"

    def _gs(self, a: list[int], t: float) -> str:
        return f":S{a[0]},{int(self._axis(a[0]).status(t))}"

    def _gvl(self, a: list[int], t: float) -> str:
        axis = self._axis(a[0])
        axis.status(t)
        return f":VL{a[0]},{round(axis.level_at(t))}"

    def _mpa(self, a: list[int], t: float) -> str | None:
        ch, target_nm, hold = a
        return self._closed_loop(ch, target_nm * 1e-9, hold, t)

    def _mpr(self, a: list[int], t: float) -> str | None:
        ch, diff_nm, hold = a
        axis = self._axis(ch)
        return self._closed_loop(ch, axis.true_position(t) + diff_nm * 1e-9, hold, t)

    def _closed_loop(self, ch: int, target: float, hold: int, t: float) -> str | None:
        axis = self._axis(ch)
        if not 0 <= hold <= 60000:
            raise _Reject(INVALID_PARAMETER, ch)
        if not axis.params.has_sensor:
            raise _Reject(NO_SENSOR, ch)
        if axis.limit is not None and not axis.limit[0] <= target <= axis.limit[1]:
            raise _Reject(RANGE_LIMIT, ch)
        lo, hi = axis.params.travel
        if not lo <= target <= hi + axis.params.fine_range:
            raise _Reject(END_STOP, ch)
        axis.move_to(target, hold, t)
        return self._ack(ch)

    def _mst(self, a: list[int], t: float) -> str | None:
        ch, steps, amplitude, frequency = a
        axis = self._axis(ch)
        if (
            abs(steps) > MAX_STEPS
            or not 0 <= amplitude <= MAX_LEVEL
            or not MIN_FREQUENCY <= frequency <= MAX_FREQUENCY
        ):
            raise _Reject(INVALID_PARAMETER, ch)
        axis.step(steps, amplitude, frequency, t)
        return self._ack(ch)

    def _msca(self, a: list[int], t: float) -> str | None:
        ch, level, speed = a
        axis = self._axis(ch)
        if not 0 <= level <= MAX_LEVEL or not MIN_SCAN_SPEED <= speed <= MAX_SCAN_SPEED:
            raise _Reject(INVALID_PARAMETER, ch)
        axis.scan(level, speed, t)
        return self._ack(ch)

    def _mscr(self, a: list[int], t: float) -> str | None:
        ch, diff, speed = a
        axis = self._axis(ch)
        axis.status(t)
        target = round(axis.level_at(t)) + diff
        if not 0 <= target <= MAX_LEVEL or not MIN_SCAN_SPEED <= speed <= MAX_SCAN_SPEED:
            raise _Reject(INVALID_PARAMETER, ch)
        axis.scan(target, speed, t)
        return self._ack(ch)

    def _stop(self, a: list[int], t: float) -> str | None:
        self._axis(a[0]).stop(t)
        return self._ack(a[0])

    def _k(self, a: list[int], t: float) -> str:
        if a[0] < 0:
            raise _Reject(INVALID_PARAMETER)
        self.watchdog_ms = a[0]
        return ":E-1,0"

    def _spl(self, a: list[int], t: float) -> str:
        ch, low, high = a
        axis = self._axis(ch)
        if high < low:
            raise _Reject(INVALID_PARAMETER, ch)
        axis.limit = None if low == high == 0 else (low * 1e-9, high * 1e-9)
        return f":E{ch},0"

    def _gpl(self, a: list[int], t: float) -> str:
        axis = self._axis(a[0])
        low, high = axis.limit or (0.0, 0.0)
        return f":PL{a[0]},{round(low * 1e9)},{round(high * 1e9)}"


Handler = Callable[[MCSDevice, list[int], float], str | None]
# longest names first, so that "SCM" is not read as "S" + "CM"
_COMMANDS: list[tuple[str, tuple[int, Handler]]] = sorted(
    {
        "SCM": (1, MCSDevice._scm),
        "GNC": (0, MCSDevice._gnc),
        "GP": (1, MCSDevice._gp),
        "GS": (1, MCSDevice._gs),
        "GVL": (1, MCSDevice._gvl),
        "MPA": (3, MCSDevice._mpa),
        "MPR": (3, MCSDevice._mpr),
        "MST": (4, MCSDevice._mst),
        "MSCA": (3, MCSDevice._msca),
        "MSCR": (3, MCSDevice._mscr),
        "S": (1, MCSDevice._stop),
        "K": (1, MCSDevice._k),
        "SPL": (3, MCSDevice._spl),
        "GPL": (1, MCSDevice._gpl),
    }.items(),
    key=lambda kv: -len(kv[0]),
)
