"""Transcript tests of the MCS driver: exactly what goes on the wire, and what comes back."""

from __future__ import annotations

import pytest

from hardware.smaract_errors import (
    EndStopError,
    MCSCommandError,
    MCSControllerError,
    MCSLinkError,
    MCSProtocolError,
    MCSTimeout,
    NoSensorError,
    PositionUnknownError,
    RangeLimitError,
)
from hardware.smaract_mcs import AxisStatus, MCSController, parse_reply
from tests.hardware.transcript import Transcript


def ctl(*pairs: tuple[bytes, bytes]) -> tuple[MCSController, Transcript]:
    link = Transcript(list(pairs))
    return MCSController(link), link


def test_every_command_on_the_wire() -> None:
    c, link = ctl(
        (b":SCM0\n", b":E-1,0\n"),
        (b":GNC\n", b":N3\n"),
        (b":GP1\n", b":P1,-1234567\n"),
        (b":GS0\n", b":S0,4\n"),
        (b":GVL2\n", b":VL2,2048\n"),
        (b":MPA0,1500,100\n", b":E0,0\n"),
        (b":MPR1,-20,0\n", b":E1,0\n"),
        (b":MST2,-30000,4095,18500\n", b":E2,0\n"),
        (b":MSCA0,4095,1000\n", b":E0,0\n"),
        (b":MSCR0,-100,50\n", b":E0,0\n"),
        (b":S1\n", b":E1,0\n"),
        (b":K500\n", b":E-1,0\n"),
        (b":SPL0,-1000000,1000000\n", b":E0,0\n"),
        (b":GPL0\n", b":PL0,-1000000,1000000\n"),
    )
    c.set_synchronous()
    assert c.channel_count() == 3
    assert c.position(1) == pytest.approx(-1.234567e-3)
    assert c.status(0) is AxisStatus.TARGETING
    assert c.voltage_level(2) == 2048
    c.move_absolute(0, 1.5e-6, hold_ms=100)
    c.move_relative(1, -20e-9)
    c.step(2, -30000, amplitude=4095, frequency=18500)
    c.scan_absolute(0, 4095, speed=1000)
    c.scan_relative(0, -100, speed=50)
    c.stop(1)
    c.set_watchdog(500)
    c.set_position_limit(0, -1e-3, 1e-3)
    assert c.position_limit(0) == pytest.approx((-1e-3, 1e-3))
    assert link.done()


@pytest.mark.parametrize(
    ("code", "error"),
    [
        (1, MCSCommandError),
        (7, MCSCommandError),
        (129, NoSensorError),
        (142, EndStopError),
        (147, RangeLimitError),
        (148, PositionUnknownError),
        (150, MCSControllerError),
    ],
)
def test_error_replies_become_typed_errors(code: int, error: type[MCSControllerError]) -> None:
    c, _ = ctl((b":MPA0,0,0\n", f":E0,{code}\n".encode()))
    with pytest.raises(error) as exc:
        c.move_absolute(0, 0.0)
    assert exc.value.code == code
    assert exc.value.channel == 0
    assert exc.value.meaning in str(exc.value)


def test_reads_are_retried_once_moves_never() -> None:
    c, link = ctl((b":GP0\n", b":#garbled\n"), (b":GP0\n", b":P0,5\n"))
    assert c.position(0) == pytest.approx(5e-9)
    assert link.flushed == 1
    c, _ = ctl((b":GS0\n", b""), (b":GS0\n", b""))
    with pytest.raises(MCSTimeout):
        c.status(0)
    c, link = ctl((b":MST0,10,100,100\n", b""))
    with pytest.raises(MCSTimeout):
        c.step(0, 10, amplitude=100, frequency=100)
    assert link.done()  # no second MST went out


def test_unexpected_and_incomplete_replies() -> None:
    c, _ = ctl((b":GP0\n", b":S0,0\n"), (b":GP0\n", b":S0,0\n"))
    with pytest.raises(MCSProtocolError, match="unexpected reply"):
        c.position(0)
    c, _ = ctl((b":MPA0,0,0\n", b":E0,"))  # cut off, no LF: the time-out hit mid-reply
    with pytest.raises(MCSTimeout, match="incomplete"):
        c.move_absolute(0, 0.0)
    c, _ = ctl((b":GS0\n", b":S0,99\n"), (b":GS0\n", b":S0,99\n"))
    with pytest.raises(MCSProtocolError, match="unknown status"):
        c.status(0)


@pytest.mark.parametrize(
    "call",
    [
        lambda c: c.step(0, 30001, amplitude=1, frequency=1),
        lambda c: c.step(0, 1, amplitude=4096, frequency=1),
        lambda c: c.step(0, 1, amplitude=1, frequency=0),
        lambda c: c.scan_absolute(0, -1, speed=1),
        lambda c: c.scan_relative(0, 1, speed=0),
        lambda c: c.move_absolute(-1, 0.0),
        lambda c: c.move_absolute(0, 0.0, hold_ms=-5),
        lambda c: c.set_position_limit(0, 1.0, 0.0),
    ],
)
def test_out_of_range_arguments_never_reach_the_wire(call) -> None:  # type: ignore[no-untyped-def]
    c, link = ctl()
    with pytest.raises(ValueError, match=r"must|below"):
        call(c)
    assert link.sent == []


def test_a_failing_transport_is_a_link_error_and_close_is_final() -> None:
    class Broken(Transcript):
        def write(self, data: bytes) -> int:
            raise OSError("cable unplugged")

    c = MCSController(Broken([]))
    with pytest.raises(MCSLinkError, match="cable unplugged"):
        c.stop(0)
    c.close()
    with pytest.raises(MCSLinkError, match="closed"):
        c.stop(0)


def test_parse_reply() -> None:
    assert parse_reply(":E-1,0").channel == -1
    assert parse_reply(":PL0,-5,7").values == (-5, 7)
    assert parse_reply(":N3").channel == 3
    with pytest.raises(MCSProtocolError):
        parse_reply("P0,1")
