"""Bruker (Veeco, Digital Instruments) NanoScope ``.spm`` / ``.000``: a text header, then the
images as little-endian integers.

The header is lines ``\\Key: value`` grouped in sections (``\\*File list``, ``\\*Scanner
list``, ``\\*Ciao scan list``, one ``\\*Ciao image list`` per image) and closed by
``\\*File list end``; each image section gives ``Data offset``, ``Data length``,
``Bytes/pixel``, ``Samps/line``, ``Number of lines`` and ``Scan Size``. A value is
``raw / 2^(8 bytes) * hard value * sensitivity``: ``\\@2:Z scale: V [Sens. Zsens] (… V/LSB)
439.9 V`` names the sensitivity (``\\@Sens. Zsens: V 20.0 nm/V`` in the scanner or scan list)
and holds the hard value (439.9 V). Heights come out in metres.

The first line stored is the bottom of the image (Gwyddion shows the array flipped), which
is this project's row 0, so rows are kept as stored. ``X offset`` / ``Y offset`` of the scan
list are the centre of the scan and become the offset of pixel (0, 0).

Written from the header's own description rather than on pySPM: its header loop never ends
on a file cut before ``*File list end``, and it pulls in plotting and notebook packages an
instrument server does not need. The tests check every value against Gwyddion's import.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from merge.io.formats.image import AfmImage, FormatError, choose_channel

MAGIC = b"\\*File list"
END = b"\\*File list end"
MAX_HEADER = 4 << 20  # bytes searched for the end of the header
IMAGE_SECTIONS = ("ciao image list", "afm image list", "ncafm image list")
_DTYPES = {1: "<i1", 2: "<i2", 4: "<i4"}
_LENGTH = {"m": 1.0, "mm": 1e-3, "~m": 1e-6, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12}
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"

Section = tuple[str, dict[str, str]]


def _sections(text: str) -> list[Section]:
    out: list[Section] = []
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("\\*"):
            out.append((line[2:].strip().lower(), {}))
            continue
        if not line.startswith("\\") or not out:
            continue
        body = line[1:]
        # "@2:Image Data: ..." carries a colon in its key
        start = 3 if re.match(r"@\d:", body) else 0
        colon = body.find(":", start)
        if colon < 0:
            continue
        out[-1][1][body[:colon].strip().lower()] = body[colon + 1 :].strip()
    return out


def _number(text: str, what: str, path: Path) -> float:
    match = re.match(_NUMBER, text.strip())
    if match is None:
        raise FormatError(f"{path}: cannot read {what} from {text!r}")
    return float(match.group())


def _scale(value: str, sensitivities: dict[str, str], path: Path) -> tuple[float, str]:
    """Factor from raw / 2^(8 bytes) to the channel's unit, and that unit (SI for lengths)."""
    # V [Sens. Zsens] (0.006713867 V/LSB) 439.9 V  -- soft scale and hard scale optional
    match = re.match(r"\w\s*(?:\[([^\]]*)\])?\s*(?:\([^)]*\))?\s*(" + _NUMBER + r")", value)
    if match is None:
        raise FormatError(f"{path}: cannot read the Z scale {value!r}")
    hard = float(match.group(2))
    soft = (match.group(1) or "").strip()
    if not soft:
        return hard, "V"
    sens = sensitivities.get("@" + soft.lower())
    if sens is None:
        raise FormatError(f"{path}: the header lacks the sensitivity {soft!r} of its Z scale")
    parts = sens.split()
    try:
        factor = float(parts[1])
    except (IndexError, ValueError):
        raise FormatError(f"{path}: cannot read the sensitivity {soft!r} from {sens!r}") from None
    unit = parts[2].removesuffix("/V") if len(parts) > 2 else "V"
    if unit in _LENGTH:
        return hard * factor * _LENGTH[unit], "m"
    return hard * factor, unit


def _size(text: str, path: Path) -> tuple[float, float]:
    """``Scan Size: 2 2 ~m`` (or one number for a square), in metres."""
    parts = text.split()
    try:
        numbers = [float(v) for v in parts[:-1]]
        unit = _LENGTH[parts[-1]]
    except (ValueError, KeyError, IndexError):
        raise FormatError(f"{path}: cannot read the scan size {text!r}") from None
    if not 1 <= len(numbers) <= 2:
        raise FormatError(f"{path}: cannot read the scan size {text!r}")
    width = numbers[0] * unit
    return width, (numbers[1] if len(numbers) == 2 else numbers[0]) * unit


def _length(text: str) -> float | None:
    """``-12.5 nm`` in metres; None when absent or not a length."""
    parts = text.split()
    if len(parts) != 2 or parts[1] not in _LENGTH:
        return None
    try:
        return float(parts[0]) * _LENGTH[parts[1]]
    except ValueError:
        return None


def _channel_names(images: list[dict[str, str]]) -> list[str]:
    names: list[str] = []
    for image in images:
        label = image.get("@2:image data", "")
        quoted = re.search(r'"([^"]*)"', label)
        bracket = re.search(r"\[([^\]]*)\]", label)
        name = (quoted.group(1) if quoted else "") or (bracket.group(1) if bracket else "")
        names.append(name or f"image {len(names)}")
    # the same signal recorded trace and retrace: tell them apart by line direction
    for name in set(names):
        same = [i for i, n in enumerate(names) if n == name]
        if len(same) > 1:
            for i in same:
                direction = images[i].get("line direction", "").strip() or f"#{i}"
                names[i] = f"{name} ({direction})"
    return names


def read_nanoscope(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One image of a NanoScope file (the height image by default), SI units."""
    p = Path(path)
    data = p.read_bytes()
    if data.startswith(b"?*File list"):
        raise FormatError(f"{p}: a NanoScope file with ASCII data: export it as binary")
    if not data.startswith(MAGIC):
        raise FormatError(f"{p}: not a Bruker NanoScope file (no \\*File list header)")
    end = data.find(END, 0, MAX_HEADER)
    if end < 0:
        raise FormatError(f"{p}: truncated header (no \\*File list end)")
    sections = _sections(data[:end].decode("latin-1"))
    images = [values for name, values in sections if name in IMAGE_SECTIONS]
    sensitivities: dict[str, str] = {}
    scan: dict[str, str] = {}
    for name, values in sections:
        if name not in IMAGE_SECTIONS:
            sensitivities.update({k: v for k, v in values.items() if k.startswith("@sens.")})
        if name in ("ciao scan list", "afm list", "nc afm list"):
            scan = values
    names = _channel_names(images)
    index = choose_channel(str(p), names, channel)
    image = images[index]
    try:
        nx = int(_number(image["samps/line"], "Samps/line", p))
        ny = int(_number(image["number of lines"], "Number of lines", p))
        offset = int(_number(image["data offset"], "Data offset", p))
        length = int(_number(image["data length"], "Data length", p))
        bpp = int(_number(image.get("bytes/pixel", "2"), "Bytes/pixel", p))
        size_text = image.get("scan size") or scan["scan size"]
        z_text = image["@2:z scale"]
    except KeyError as exc:
        raise FormatError(f"{p}: image {names[index]!r} lacks {exc.args[0]!r}") from None
    if bpp not in _DTYPES or nx < 1 or ny < 1 or offset < 0:
        raise FormatError(
            f"{p}: unsupported image layout ({nx} x {ny}, {bpp} bytes/pixel at {offset})"
        )
    if length < nx * ny * bpp:
        raise FormatError(
            f"{p}: image {names[index]!r} holds {length} bytes, needs {nx * ny * bpp}"
        )
    if offset + nx * ny * bpp > len(data):
        raise FormatError(f"{p}: truncated: image {names[index]!r} is cut short")
    raw = np.frombuffer(data, dtype=_DTYPES[bpp], count=nx * ny, offset=offset)
    factor, unit = _scale(z_text, sensitivities, p)
    heights = raw.reshape(ny, nx).astype(np.float64) * (factor / 2.0 ** (8 * bpp))
    width, height = _size(size_text, p)
    dx, dy = width / nx, height / ny
    cx, cy = _length(scan.get("x offset", "")), _length(scan.get("y offset", ""))
    origin = None
    if cx is not None and cy is not None:
        origin = (cx - width / 2 + dx / 2, cy - height / 2 + dy / 2)
    return AfmImage(
        heights=heights,
        pixel_size=(dx, dy),
        channel=names[index],
        unit=unit,
        offset=origin,
        channels=tuple(names),
    )
