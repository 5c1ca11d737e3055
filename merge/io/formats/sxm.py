"""Nanonis ``.sxm``: a text header of ``:KEY:`` blocks up to ``:SCANIT_END:``, the marker
``0x1A 0x04``, then every channel's frames (forward, and backward when recorded) as
big-endian float32 in physical units.

``SCAN_OFFSET`` is the centre of the frame; ``SCAN_DIR`` says whether the first stored line
is the bottom (``up``) or the top (``down``); backward frames are stored right to left. All
three are undone here (rows along +y, x along +x), as Gwyddion does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from merge.io.formats.image import AfmImage, FormatError, choose_channel

MARKER = b"\x1a\x04"


def _header(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    key = None
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith(":") and stripped.endswith(":") and len(stripped) > 1:
            key = stripped[1:-1]
            out[key] = []
        elif key is not None and stripped:
            out[key].append(line)
    return out


def read_sxm(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One frame of a Nanonis ``.sxm`` file (``Z forward`` by default), SI units."""
    p = Path(path)
    data = p.read_bytes()
    end = data.find(b":SCANIT_END:")
    start = data.find(MARKER, end) if end >= 0 else -1
    if not data.startswith(b":NANONIS_VERSION:") or start < 0:
        raise FormatError(f"{p}: not a Nanonis .sxm file (no :NANONIS_VERSION: header)")
    header = _header(data[:end].decode("latin-1"))
    try:
        nx, ny = (int(float(v)) for v in header["SCAN_PIXELS"][0].split())
        wx, wy = (float(v) for v in header["SCAN_RANGE"][0].split())
        cx, cy = (float(v) for v in header.get("SCAN_OFFSET", ["0 0"])[0].split())
        up = header.get("SCAN_DIR", ["down"])[0].strip().lower() == "up"
        rows = [line.strip().split("\t") for line in header["DATA_INFO"][1:]]
    except (KeyError, ValueError, IndexError):
        raise FormatError(f"{p}: the header lacks SCAN_PIXELS, SCAN_RANGE or DATA_INFO") from None
    frames: list[tuple[str, str, bool]] = []  # (name, unit, backward)
    for row in rows:
        if len(row) < 4:
            continue
        name, unit, direction = row[1], row[2], row[3].lower()
        frames.append((f"{name} forward", unit, False))
        if direction == "both":
            frames.append((f"{name} backward", unit, True))
    names = [f[0] for f in frames]
    index = choose_channel(str(p), names, channel)
    size = nx * ny * 4
    offset = start + len(MARKER) + index * size
    if offset + size > len(data):
        raise FormatError(f"{p}: truncated: frame {names[index]!r} is cut short")
    frame = np.frombuffer(data, dtype=">f4", count=nx * ny, offset=offset).reshape(ny, nx)
    heights = np.asarray(frame, dtype=np.float64)
    if not up:
        heights = heights[::-1]  # stored top line first
    if frames[index][2]:
        heights = heights[:, ::-1]  # backward lines run right to left
    dx, dy = wx / nx, wy / ny
    return AfmImage(
        heights=heights.copy(),
        pixel_size=(dx, dy),
        channel=names[index],
        unit=frames[index][1],
        offset=(cx - wx / 2 + dx / 2, cy - wy / 2 + dy / 2),
        channels=tuple(names),
    )
