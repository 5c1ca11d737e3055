"""The wire format, pinned byte for byte where the manual fixes it, and round trips."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hardware.nanonis import wire
from hardware.nanonis.errors import NanonisProtocolError


def test_a_request_is_the_40_byte_header_then_the_body() -> None:
    message = wire.request("PLL.FreqShiftGet", "i", [1])
    name = b"PLL.FreqShiftGet".ljust(32, b"\0")
    assert message == name + b"\x00\x00\x00\x04" + b"\x00\x01" + b"\x00\x00" + b"\x00\x00\x00\x01"


def test_a_response_ends_with_its_error_block() -> None:
    message = wire.response("ZCtrl.ZPosGet", "f", [1.5e-7])
    header = wire.decode_header(message[:40])
    assert (header.command, header.body_size) == ("ZCtrl.ZPosGet", 12)
    assert message[40:44] == struct.pack(">f", 1.5e-7)
    assert message[44:] == b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00"  # status 0, no text
    refused = wire.response("Scan.Action", status=1, description="no")
    assert refused[40:] == b"\x00\x00\x00\x01\x00\x00\x00\x02no"


def test_typed_fields_round_trip() -> None:
    types = ["i", "I", "H", "f", "d", "s", "ai", "as", "2f"]
    frame = np.arange(6, dtype=np.float64).reshape(2, 3) * 0.5
    values = [-3, 7, 65535, 0.25, 1e-9, "Z (m)", [14, 15], ["a", "bcd"], frame]
    body = wire.encode(types, values)
    out, used = wire.decode(types, body)
    assert used == len(body)
    assert out[:8] == values[:8]
    np.testing.assert_array_equal(out[8], frame)


def test_string_arrays_count_their_size_as_the_manual_says() -> None:
    body = wire.encode(["as"], [["ab", "c"]])
    # size of what follows the count: (4 + 2) + (4 + 1)
    assert body[:8] == b"\x00\x00\x00\x0b\x00\x00\x00\x02"


@pytest.mark.parametrize(
    "body",
    [
        b"",  # no error block at all
        b"\x00\x00\x00",  # a value cut short
        b"\x3f\x80\x00\x00\x00\x00\x00\x00",  # value and status, no description size
        b"\x3f\x80\x00\x00\x00\x00\x00\x01\x00\x00\x00\x09short",  # description cut short
        b"\x3f\x80\x00\x00" + bytes(8) + b"extra",  # bytes after the error block
    ],
)
def test_malformed_and_short_responses_are_protocol_errors(body: bytes) -> None:
    with pytest.raises(NanonisProtocolError):
        wire.decode_response("f", body, command="PLL.FreqShiftGet")


@pytest.mark.parametrize(
    "raw",
    [b"\x00" * 40, b"\xff" * 40, b"PLL".ljust(32, b"\0") + b"\x7f\xff\xff\xff" + bytes(4), b"x"],
)
def test_garbled_headers_are_protocol_errors(raw: bytes) -> None:
    with pytest.raises(NanonisProtocolError):
        wire.decode_header(raw)


def test_bad_requests_are_refused_before_sending() -> None:
    with pytest.raises(ValueError, match="32"):
        wire.encode_header("X" * 33, 0)
    with pytest.raises(ValueError, match="not a valid"):
        wire.encode("H", [70000])
    with pytest.raises(ValueError, match="2 types for 1"):
        wire.encode("ii", [1])


@given(
    st.lists(st.floats(width=32, allow_nan=False), max_size=20),
    st.text(max_size=30),
    st.integers(-(2**31), 2**31 - 1),
)
def test_any_value_survives_the_wire(floats: list[float], text: str, n: int) -> None:
    out, _ = wire.decode(["af", "s", "i"], wire.encode(["af", "s", "i"], [floats, text, n]))
    assert out[0].tolist() == floats and out[1] == text and out[2] == n
