"""Transcript tests of every command the driver sends: (bytes sent, bytes answered) pairs."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from hardware.nanonis import wire
from hardware.nanonis.client import NanonisClient
from hardware.nanonis.errors import (
    NanonisCommandError,
    NanonisLinkError,
    NanonisProtocolError,
    NanonisTimeout,
)


class Transcript:
    """Plays the controller's side: each ``sendall`` must be the next expected request; the
    reply (bytes, or an exception to raise on ``recv``) is then read back."""

    def __init__(self, pairs: list[tuple[bytes, bytes | BaseException]]) -> None:
        self.pairs = list(pairs)
        self.pending = b""
        self.error: BaseException | None = None
        self.closed = False

    def sendall(self, data: bytes) -> None:
        assert self.pairs, f"unexpected request {data[:32]!r}: the transcript is over"
        expected, reply = self.pairs.pop(0)
        assert data == expected, f"sent {data!r}, expected {expected!r}"
        if isinstance(reply, BaseException):
            self.error = reply
        else:
            self.pending += reply

    def recv(self, size: int) -> bytes:
        if self.error is not None:
            raise self.error
        chunk, self.pending = self.pending[:size], self.pending[size:]
        return chunk

    def settimeout(self, value: float | None) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def client_on(*streams: Transcript) -> NanonisClient:
    queue = list(streams)
    return NanonisClient(lambda: queue.pop(0), name="transcript")


# (call, command, argument types, arguments, reply types, reply values, expected result)
CASES: list[tuple[Callable[[NanonisClient], Any], str, Any, list[Any], Any, list[Any], Any]] = [
    (lambda c: c.frequency_shift(), "PLL.FreqShiftGet", "i", [1], "f", [-2.5], -2.5),
    (lambda c: c.frequency_range(), "PLL.FreqRangeGet", "i", [1], "f", [500.0], 500.0),
    (
        lambda c: c.amplitude_setpoint(),
        "PLL.AmpCtrlSetpntGet",
        "i",
        [1],
        "f",
        [1e-8],
        pytest.approx(1e-8),
    ),
    (
        lambda c: c.signal_names(),
        "Signals.NamesGet",
        "",
        [],
        ["as"],
        [["Z (m)", "Bias (V)"]],
        ["Z (m)", "Bias (V)"],
    ),
    (lambda c: c.signal_value(4), "Signals.ValGet", "iI", [4, 0], "f", [0.5], 0.5),
    (lambda c: c.z_controller(True), "ZCtrl.OnOffSet", "I", [1], "", [], None),
    (lambda c: c.z_controller(False), "ZCtrl.OnOffSet", "I", [0], "", [], None),
    (lambda c: c.z_controller_on(), "ZCtrl.OnOffGet", "", [], "I", [1], True),
    (lambda c: c.set_setpoint(10.0), "ZCtrl.SetpntSet", "f", [10.0], "", [], None),
    (lambda c: c.setpoint(), "ZCtrl.SetpntGet", "", [], "f", [10.0], 10.0),
    (lambda c: c.z_position(), "ZCtrl.ZPosGet", "", [], "f", [0.25], 0.25),
    (lambda c: c.set_z_position(0.5), "ZCtrl.ZPosSet", "f", [0.5], "", [], None),
    (lambda c: c.z_limits(), "ZCtrl.LimitsGet", "", [], "ff", [0.5, -0.5], (0.5, -0.5)),
    (lambda c: c.withdraw(), "ZCtrl.Withdraw", "Ii", [1, 5000], "", [], None),
    (lambda c: c.piezo_range(), "Piezo.RangeGet", "", [], "fff", [2.0, 2.0, 1.0], (2.0, 2.0, 1.0)),
    (lambda c: c.tip_xy(), "FolMe.XYPosGet", "I", [0], "dd", [1e-7, -1e-7], (1e-7, -1e-7)),
    (lambda c: c.move_tip(1e-7, 2e-7), "FolMe.XYPosSet", "ddI", [1e-7, 2e-7, 1], "", [], None),
    (lambda c: c.set_tip_speed(1e-6), "FolMe.SpeedSet", "fI", [1e-6, 1], "", [], None),
    (lambda c: c.stop_tip(), "FolMe.Stop", "", [], "", [], None),
    (
        lambda c: c.set_frame((0.0, 0.0), (0.5, 0.25), 0.0),
        "Scan.FrameSet",
        "fffff",
        [0.0, 0.0, 0.5, 0.25, 0.0],
        "",
        [],
        None,
    ),
    (
        lambda c: c.frame(),
        "Scan.FrameGet",
        "",
        [],
        "fffff",
        [0.0, 0.0, 0.5, 0.25, 0.0],
        (0.0, 0.0, 0.5, 0.25, 0.0),
    ),
    (
        lambda c: c.set_buffer([14], 32, 16),
        "Scan.BufferSet",
        ["ai", "i", "i"],
        [[14], 32, 16],
        "",
        [],
        None,
    ),
    (
        lambda c: c.buffer(),
        "Scan.BufferGet",
        "",
        [],
        ["ai", "i", "i"],
        [[14], 32, 16],
        ([14], 32, 16),
    ),
    (
        lambda c: c.set_speed(0.5, 0.25, 1.0),
        "Scan.SpeedSet",
        "ffffHf",
        [2.0, 4.0, 0.5, 0.25, 2, 2.0],
        "",
        [],
        None,
    ),
    (
        lambda c: c.speed(),
        "Scan.SpeedGet",
        "",
        [],
        "ffffHf",
        [2.0, 4.0, 0.5, 0.25, 1, 2.0],
        (2.0, 4.0, 0.5, 0.25, 1, 2.0),
    ),
    (lambda c: c.scan_action(0), "Scan.Action", "HI", [0, 1], "", [], None),
    (lambda c: c.scan_action(1), "Scan.Action", "HI", [1, 1], "", [], None),
    (lambda c: c.scanning(), "Scan.StatusGet", "", [], "I", [1], True),
    (
        lambda c: c.wait_end_of_scan(0.25),
        "Scan.WaitEndOfScan",
        "i",
        [250],
        ["I", "s"],
        [1, ""],
        False,
    ),
    (lambda c: c.auto_approach(True), "AutoApproach.OnOffSet", "H", [1], "", [], None),
    (lambda c: c.auto_approach_running(), "AutoApproach.OnOffGet", "", [], "H", [0], False),
    (lambda c: c.motor_move("Z-", 6), "Motor.StartMove", "IHII", [5, 6, 0, 1], "", [], None),
    (
        lambda c: c.motor_move_to((1e-6, 2e-6, 0.0)),
        "Motor.StartClosedLoop",
        "IdddII",
        [1, 1e-6, 2e-6, 0.0, 1, 0],
        "",
        [],
        None,
    ),
    (
        lambda c: c.motor_position(),
        "Motor.PosGet",
        "II",
        [0, 500],
        "ddd",
        [1.0, 2.0, 3.0],
        (1.0, 2.0, 3.0),
    ),
    (lambda c: c.motor_stop(), "Motor.StopMove", "", [], "", [], None),
]


@pytest.mark.parametrize("case", CASES, ids=[c[1] for c in CASES])
def test_every_command_sends_its_bytes_and_decodes_its_reply(case: tuple[Any, ...]) -> None:
    call, command, arg_types, args, reply_types, reply, expected = case
    t = Transcript(
        [(wire.request(command, arg_types, args), wire.response(command, reply_types, reply))]
    )
    assert call(client_on(t)) == expected
    assert not t.pairs


def test_a_frame_grab_decodes_the_2d_array() -> None:
    data = np.arange(12, dtype=np.float64).reshape(3, 4) * 1e-9
    t = Transcript(
        [
            (
                wire.request("Scan.FrameDataGrab", "II", [14, 1]),
                wire.response("Scan.FrameDataGrab", ["s", "2f", "I"], ["Z (m)", data, 1]),
            )
        ]
    )
    name, got, up = client_on(t).grab_frame(14)
    assert (name, up) == ("Z (m)", True)
    np.testing.assert_allclose(got, data, rtol=1e-6)


def test_an_error_block_is_a_command_error_with_its_text() -> None:
    t = Transcript(
        [
            (
                wire.request("ZCtrl.OnOffSet", "I", [1]),
                wire.response("ZCtrl.OnOffSet", status=5, description="no signal"),
            )
        ]
    )
    with pytest.raises(NanonisCommandError, match="no signal") as caught:
        client_on(t).z_controller(True)
    assert caught.value.status == 5


def test_a_short_reply_drops_the_link_and_a_read_is_retried_on_a_new_one() -> None:
    request = wire.request("ZCtrl.ZPosGet", (), ())
    good = wire.response("ZCtrl.ZPosGet", "f", [0.125])
    first = Transcript([(request, good[:45])])  # cut inside the error block, then EOF
    second = Transcript([(request, good)])
    client = client_on(first, second)
    assert client.z_position() == 0.125
    assert first.closed and not second.pairs


def test_a_move_is_never_sent_twice() -> None:
    request = wire.request("Motor.StartMove", "IHII", [5, 6, 0, 1])
    t = Transcript([(request, ConnectionResetError("reset by peer"))])
    with pytest.raises(NanonisLinkError, match="reset by peer"):
        client_on(t).motor_move("Z-", 6)
    assert t.closed


def test_a_time_out_is_typed_and_the_stream_abandoned() -> None:
    request = wire.request("PLL.FreqShiftGet", "i", [1])
    a, b = Transcript([(request, TimeoutError())]), Transcript([(request, TimeoutError())])
    with pytest.raises(NanonisTimeout, match=r"no response to PLL\.FreqShiftGet"):
        client_on(a, b).frequency_shift()
    assert a.closed and b.closed


def test_a_reply_to_another_command_is_a_protocol_error() -> None:
    t = Transcript([(wire.request("Scan.Action", "HI", [0, 1]), wire.response("Scan.StatusGet"))])
    with pytest.raises(NanonisProtocolError, match=r"Scan\.StatusGet"):
        client_on(t).scan_action(0)


def test_a_reply_of_the_wrong_shape_is_a_protocol_error() -> None:
    t = Transcript(
        [(wire.request("Scan.Action", "HI", [0, 1]), wire.response("Scan.Action", "f", [1.0]))]
    )
    with pytest.raises(NanonisProtocolError, match="unexpected bytes"):
        client_on(t).scan_action(0)


def test_a_closed_client_refuses_and_a_dead_address_says_where() -> None:
    client = client_on()
    client.close()
    with pytest.raises(NanonisLinkError, match="closed"):
        client.setpoint()
    with pytest.raises(NanonisLinkError, match=r"127\.0\.0\.1:1"):
        NanonisClient.open("127.0.0.1", 1, timeout=0.5)
    with pytest.raises(ValueError, match="Z-"):
        client_on().motor_move("W+", 1)


def test_a_refusal_of_a_read_keeps_its_layout_and_is_a_command_error() -> None:
    refused = wire.response(
        "ZCtrl.ZPosGet", "f", wire.placeholders("f"), status=3, description="Z is off"
    )
    t = Transcript([(wire.request("ZCtrl.ZPosGet", (), ()), refused)])
    with pytest.raises(NanonisCommandError, match="Z is off"):
        client_on(t).z_position()
