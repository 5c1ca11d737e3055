"""The SharkSEM wire format: headers and typed bodies, both ways, and what does not parse."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hardware.sharksem import wire
from hardware.sharksem.errors import SharkSEMProtocolError


def test_a_header_is_the_name_padded_then_little_endian_fields() -> None:
    raw = wire.encode_header("GetViewField", 8, message_id=7, flags=wire.RESPOND | wire.WAIT_SCAN)
    assert raw == (
        b"GetViewField\0\0\0\0" + (8).to_bytes(4, "little") + (7).to_bytes(4, "little")
        + (0x0101).to_bytes(2, "little") + b"\0\0" + b"\0\0\0\0"
    )  # fmt: skip
    header = wire.decode_header(raw)
    assert header == wire.Header("GetViewField", 8, 7, 0x0101, 0) and header.respond


def test_floats_and_strings_are_text_with_their_size_padded_to_four_bytes() -> None:
    body = wire.encode("ifsb", [-3, 0.0125, "SE", b"\x01\x02\x03"])
    assert body == (
        (-3).to_bytes(4, "little", signed=True)
        + (6).to_bytes(4, "little") + b"0.0125\0\0"
        + (2).to_bytes(4, "little") + b"SE\0\0"
        + (3).to_bytes(4, "little") + b"\x01\x02\x03\0"
    )  # fmt: skip
    assert wire.decode("ifsb", body) == [-3, 0.0125, "SE", b"\x01\x02\x03"]


@given(
    st.lists(st.integers(-(2**31), 2**31 - 1), max_size=4),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=40),
    st.binary(max_size=33),
)
def test_every_field_comes_back_as_it_went(
    ints: list[int], value: float, text: str, data: bytes
) -> None:
    types = "i" * len(ints) + "fsb"
    body = wire.encode(types, [*ints, value, text, data])
    assert len(body) % 4 == 0
    assert wire.decode(types, body) == [*ints, value, text, data]


def test_what_does_not_parse_is_a_protocol_error() -> None:
    with pytest.raises(SharkSEMProtocolError, match="too short"):
        wire.decode("ii", b"\0\0\0\0")
    with pytest.raises(SharkSEMProtocolError, match="is not a 'f'"):
        wire.decode("f", wire.encode("s", ["fast"]))
    with pytest.raises(SharkSEMProtocolError, match="garbled"):
        wire.decode_header(b"\x07garbled" + bytes(24))
    with pytest.raises(SharkSEMProtocolError, match="not one"):
        wire.decode_header(wire.encode_header("ScData", 3))
    with pytest.raises(ValueError, match="1 to 16"):
        wire.encode_header("AVeryLongCommandName", 0)
