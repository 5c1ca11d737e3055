"""The TESCAN SharkSEM wire format: a message's header and its typed body. Pure functions.

Every message (request, reply, and the image data that stream on the data connection) is a
32-byte header then a body. The header, little-endian: the command name (16 bytes, ASCII,
NUL-padded), the body size (uint32), a message id (uint32), flags (uint16: bit 0 asks for a
reply, bits 8-15 are the wait flags: what the SEM must have finished before it runs the
command), the queue (uint16) and a reserved uint32.

Body fields, as this module names them (all little-endian, every field a multiple of 4 bytes):

====== ===================================================================================
code   on the wire
====== ===================================================================================
i I    int32, uint32
f      a float, as text: uint32 size in bytes, then ASCII digits, NUL-padded to 4 bytes
s      a string: uint32 size in bytes, then the ASCII text, NUL-padded to 4 bytes
b      bytes (an image's pixels): uint32 size in bytes, then the bytes, padded to 4 bytes
====== ===================================================================================
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from hardware.sharksem.errors import SharkSEMProtocolError

#: command name (16 bytes), body size, message id, flags, queue, reserved
HEADER = struct.Struct("<16sIIHHI")
HEADER_SIZE = HEADER.size  # 32
#: The flag that asks for a reply.
RESPOND = 0x0001
#: Wait flags (bits 8-15): before the command runs, the SEM finishes its scanning (A), its
#: stage move (B), its optics (C), an automatic procedure (D).
WAIT_SCAN, WAIT_STAGE, WAIT_OPTICS, WAIT_AUTO = (1 << 8, 1 << 9, 1 << 10, 1 << 11)
#: Largest body either side accepts (a 4096 x 4096 16-bit frame and change).
MAX_BODY = 40 * 1024 * 1024

_SCALARS = {"i": struct.Struct("<i"), "I": struct.Struct("<I")}
_SIZE = struct.Struct("<I")


@dataclass(frozen=True)
class Header:
    """A parsed header: the command, the body size that follows, the id, flags and queue."""

    command: str
    body_size: int
    message_id: int = 0
    flags: int = 0
    queue: int = 0

    @property
    def respond(self) -> bool:
        return bool(self.flags & RESPOND)


def _padded(data: bytes) -> bytes:
    return _SIZE.pack(len(data)) + data + b"\0" * (-len(data) % 4)


def encode_header(
    command: str, body_size: int, *, message_id: int = 0, flags: int = 0, queue: int = 0
) -> bytes:
    """The 32-byte header of a message of ``body_size`` bytes."""
    name = command.encode("ascii")
    if not 0 < len(name) <= 16:
        raise ValueError(f"a command name has 1 to 16 ASCII characters, got {command!r}")
    return HEADER.pack(name, body_size, message_id, flags, queue, 0)


def decode_header(raw: bytes) -> Header:
    """Parse a header; :class:`SharkSEMProtocolError` if it is not one."""
    if len(raw) != HEADER_SIZE:
        raise SharkSEMProtocolError(f"a header is {HEADER_SIZE} bytes, got {len(raw)}")
    name, size, message_id, flags, queue, _ = HEADER.unpack(raw)
    try:
        command = name.rstrip(b"\0").decode("ascii")
    except UnicodeDecodeError:
        raise SharkSEMProtocolError(f"garbled command name in header: {name!r}") from None
    if not command or "\0" in command or not command.isprintable():
        raise SharkSEMProtocolError(f"garbled command name in header: {name!r}")
    if size > MAX_BODY or size % 4:
        raise SharkSEMProtocolError(f"{command}: a body of {size} bytes is not one")
    return Header(command, size, message_id, flags, queue)


def encode(types: str | Sequence[str], values: Sequence[Any]) -> bytes:
    """Encode ``values`` as body fields of ``types`` (see the module notes)."""
    if len(types) != len(values):
        raise ValueError(f"{len(types)} types for {len(values)} values")
    out = bytearray()
    for code, value in zip(types, values, strict=True):
        if code in _SCALARS:
            try:
                out += _SCALARS[code].pack(value)
            except struct.error as exc:
                raise ValueError(f"{value!r} is not a valid {code!r}: {exc}") from None
        elif code == "f":
            out += _padded(repr(float(value)).encode("ascii"))
        elif code == "s":
            out += _padded(str(value).encode("ascii"))
        elif code == "b":
            out += _padded(bytes(value))
        else:
            raise ValueError(f"unknown field type {code!r}")
    return bytes(out)


def decode(types: str | Sequence[str], body: bytes, *, what: str = "body") -> list[Any]:
    """Decode fields of ``types`` from ``body`` (strings as ``str``, floats as ``float``,
    bytes as ``bytes``); a body too short or a field that does not parse is a
    :class:`SharkSEMProtocolError` naming ``what``."""
    at, out = 0, []

    def take(n: int) -> bytes:
        nonlocal at
        if n < 0 or at + n > len(body):
            raise SharkSEMProtocolError(
                f"{what}: body too short ({len(body)} bytes; needed {at + n})"
            )
        chunk = body[at : at + n]
        at += n
        return chunk

    for code in types:
        if code in _SCALARS:
            out.append(_SCALARS[code].unpack(take(4))[0])
            continue
        if code not in "fsb":
            raise ValueError(f"unknown field type {code!r}")
        size = _SIZE.unpack(take(4))[0]
        data = take(size)
        take(-size % 4)
        if code == "b":
            out.append(data)
            continue
        text = data.rstrip(b"\0")
        try:
            value = text.decode("ascii")
            out.append(float(value) if code == "f" else value)
        except (UnicodeDecodeError, ValueError):
            raise SharkSEMProtocolError(f"{what}: {text[:40]!r} is not a {code!r}") from None
    return out


def message(
    command: str,
    types: str = "",
    values: Sequence[Any] = (),
    *,
    message_id: int = 0,
    flags: int = 0,
    queue: int = 0,
) -> bytes:
    """A whole message: header and body."""
    body = encode(types, values)
    head = encode_header(command, len(body), message_id=message_id, flags=flags, queue=queue)
    return head + body
