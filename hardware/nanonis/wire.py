"""The Nanonis TCP wire format: header, typed bodies and the error block. Pure functions.

Every message starts with a 40-byte header, big-endian: the command name (32 bytes, ASCII,
NUL-padded), the body size (uint32), the "send response back" flag (uint16) and two unused
bytes. A request body holds the arguments; a response body holds the return values followed
by the error block that every response carries: error status (int32, 0 = none), description
size (int32) and the description (bytes).

Types of body fields, as this module names them:

====== ===================================================================================
code   on the wire
====== ===================================================================================
i I    int32, uint32
h H    int16, uint16
f d    float32, float64
s      string: int32 size in bytes, then the bytes (UTF-8)
ai aI  1-D array of int32 (uint32): int32 count, then the elements
af ad  1-D array of float32 (float64): int32 count, then the elements
as     array of strings: int32 size of what follows the count in bytes, int32 count, then
       each string as ``s``
2f     2-D array of float32: int32 rows, int32 columns, then the elements row by row
====== ===================================================================================
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hardware.nanonis.errors import NanonisProtocolError

#: name (32 bytes), body size, response flag, unused
HEADER = struct.Struct(">32sIHH")
HEADER_SIZE = HEADER.size  # 40
#: Largest body either side accepts (a 4096 x 4096 float32 frame and change).
MAX_BODY = 80 * 1024 * 1024

_SCALARS = {"i": ">i", "I": ">I", "h": ">h", "H": ">H", "f": ">f", "d": ">d"}
_ARRAYS = {"ai": ">i4", "aI": ">u4", "af": ">f4", "ad": ">f8"}
_COUNT = struct.Struct(">i")


@dataclass(frozen=True)
class Header:
    """A parsed header: the command it names, the body size that follows, the flag."""

    command: str
    body_size: int
    respond: bool


def encode_header(command: str, body_size: int, *, respond: bool = True) -> bytes:
    """The 40-byte header of a message of ``body_size`` bytes."""
    name = command.encode("ascii")
    if not 0 < len(name) <= 32:
        raise ValueError(f"a command name has 1 to 32 ASCII characters, got {command!r}")
    return HEADER.pack(name, body_size, 1 if respond else 0, 0)


def decode_header(raw: bytes) -> Header:
    """Parse a header; :class:`NanonisProtocolError` if it is not one."""
    if len(raw) != HEADER_SIZE:
        raise NanonisProtocolError(f"a header is {HEADER_SIZE} bytes, got {len(raw)}")
    name, size, flag, _ = HEADER.unpack(raw)
    try:
        command = name.rstrip(b"\0").decode("ascii")
    except UnicodeDecodeError:
        raise NanonisProtocolError(f"garbled command name in header: {name!r}") from None
    if not command or "\0" in command or not command.isprintable():
        raise NanonisProtocolError(f"garbled command name in header: {name!r}")
    if size > MAX_BODY:
        raise NanonisProtocolError(f"{command}: body of {size} bytes is beyond {MAX_BODY}")
    return Header(command, size, bool(flag))


def encode(types: Sequence[str], values: Sequence[Any]) -> bytes:
    """Encode ``values`` as body fields of ``types`` (see the module notes)."""
    if len(types) != len(values):
        raise ValueError(f"{len(types)} types for {len(values)} values")
    out = bytearray()
    for code, value in zip(types, values, strict=True):
        if code in _SCALARS:
            try:
                out += struct.pack(_SCALARS[code], value)
            except struct.error as exc:
                raise ValueError(f"{value!r} is not a valid {code!r}: {exc}") from None
        elif code == "s":
            data = str(value).encode("utf-8")
            out += _COUNT.pack(len(data)) + data
        elif code in _ARRAYS:
            arr = np.asarray(value, dtype=_ARRAYS[code]).reshape(-1)
            out += _COUNT.pack(arr.size) + arr.tobytes()
        elif code == "as":
            items = b"".join(_COUNT.pack(len(b)) + b for b in (str(v).encode() for v in value))
            out += _COUNT.pack(len(items)) + _COUNT.pack(len(value)) + items
        elif code == "2f":
            arr = np.asarray(value, dtype=">f4")
            if arr.ndim != 2:
                raise ValueError(f"a 2f field needs a 2-D array, got shape {arr.shape}")
            shape: tuple[int, ...] = arr.shape
            rows, cols = shape
            out += _COUNT.pack(rows) + _COUNT.pack(cols) + arr.tobytes()
        else:
            raise ValueError(f"unknown field type {code!r}")
    return bytes(out)


class _Reader:
    def __init__(self, body: bytes, what: str) -> None:
        self.body, self.at, self.what = body, 0, what

    def take(self, n: int) -> bytes:
        if n < 0 or self.at + n > len(self.body):
            raise NanonisProtocolError(
                f"{self.what}: body too short ({len(self.body)} bytes; needed {self.at + n})"
            )
        chunk = self.body[self.at : self.at + n]
        self.at += n
        return chunk

    def count(self) -> int:
        n: int = _COUNT.unpack(self.take(4))[0]
        if n < 0:
            raise NanonisProtocolError(f"{self.what}: negative size {n}")
        return n


def decode(types: Sequence[str], body: bytes, *, what: str = "body") -> tuple[list[Any], int]:
    """Decode fields of ``types`` from the start of ``body``; return them and the bytes used.

    Strings come back as ``str``, integer arrays as lists, float arrays as float64 numpy
    arrays (2-D for ``2f``). A body too short for its fields is a
    :class:`NanonisProtocolError`.
    """
    r = _Reader(body, what)
    out: list[Any] = []
    for code in types:
        if code in _SCALARS:
            fmt = _SCALARS[code]
            out.append(struct.unpack(fmt, r.take(struct.calcsize(fmt)))[0])
        elif code == "s":
            out.append(r.take(r.count()).decode("utf-8", errors="replace"))
        elif code in _ARRAYS:
            dtype = np.dtype(_ARRAYS[code])
            arr = np.frombuffer(r.take(r.count() * dtype.itemsize), dtype=dtype)
            out.append(arr.astype(np.float64) if code in ("af", "ad") else arr.tolist())
        elif code == "as":
            size, n = r.count(), r.count()
            block = _Reader(r.take(size), what)
            out.append([block.take(block.count()).decode("utf-8", "replace") for _ in range(n)])
        elif code == "2f":
            rows, cols = r.count(), r.count()
            arr = np.frombuffer(r.take(rows * cols * 4), dtype=">f4").reshape(rows, cols)
            out.append(arr.astype(np.float64))
        else:
            raise ValueError(f"unknown field type {code!r}")
    return out, r.at


def placeholders(types: Sequence[str]) -> list[Any]:
    """Default values of ``types`` (zeros, empty strings and arrays): what a response that
    refuses its command carries before its error block, so its layout stays the same."""
    out: list[Any] = []
    for code in types:
        if code in _SCALARS:
            out.append(0)
        elif code == "s":
            out.append("")
        elif code == "2f":
            out.append(np.zeros((0, 0)))
        elif code in _ARRAYS or code == "as":
            out.append([])
        else:
            raise ValueError(f"unknown field type {code!r}")
    return out


def encode_error(status: int = 0, description: str = "") -> bytes:
    """The error block that ends every response body."""
    text = description.encode("utf-8")
    return struct.pack(">ii", status, len(text)) + text


def decode_response(
    types: Sequence[str], body: bytes, *, command: str
) -> tuple[list[Any], int, str]:
    """Return values, error status and description of a response body.

    The error block must follow the values exactly; anything else is a
    :class:`NanonisProtocolError` (a short reply, or values of another shape than expected).
    """
    values, used = decode(types, body, what=command)
    r = _Reader(body[used:], f"{command} error block")
    status: int = struct.unpack(">i", r.take(4))[0]
    description = r.take(r.count()).decode("utf-8", errors="replace")
    if r.at != len(r.body):
        raise NanonisProtocolError(
            f"{command}: {len(r.body) - r.at} unexpected bytes after the error block"
        )
    return values, status, description


def request(command: str, types: Sequence[str], values: Sequence[Any]) -> bytes:
    """A whole request message (header and body), asking for a response."""
    body = encode(types, values)
    return encode_header(command, len(body)) + body


def response(
    command: str,
    types: Sequence[str] = (),
    values: Sequence[Any] = (),
    *,
    status: int = 0,
    description: str = "",
) -> bytes:
    """A whole response message: header, return values, error block."""
    body = encode(types, values) + encode_error(status, description)
    return encode_header(command, len(body), respond=False) + body
