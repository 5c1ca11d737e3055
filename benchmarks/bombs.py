"""Files that promise more than they hold: what the safety benchmark and tests send."""

from __future__ import annotations

import struct
import zlib


def tiff_declaring(width: int, height: int) -> bytes:
    """A TIFF of a few hundred bytes that declares ``width`` x ``height`` 8-bit pixels in
    one deflated strip (what decompression bombs look like: the header promises gigabytes)."""
    strip = zlib.compress(bytes(4096))
    tags = [  # (tag, type, count, value): SHORT 3, LONG 4
        (256, 4, 1, width),
        (257, 4, 1, height),
        (258, 3, 1, 8),
        (259, 3, 1, 8),  # deflate
        (262, 3, 1, 1),
        (273, 4, 1, 0),  # strip offset, filled in below
        (277, 3, 1, 1),
        (278, 4, 1, height),
        (279, 4, 1, len(strip)),
    ]
    ifd_at = 8
    data_at = ifd_at + 2 + 12 * len(tags) + 4
    out = bytearray(b"II*\x00" + struct.pack("<I", ifd_at))
    out += struct.pack("<H", len(tags))
    for tag, kind, count, value in tags:
        value = data_at if tag == 273 else value
        packed = struct.pack("<H", value) + b"\0\0" if kind == 3 else struct.pack("<I", value)
        out += struct.pack("<HHI", tag, kind, count) + packed
    out += struct.pack("<I", 0) + strip
    return bytes(out)
