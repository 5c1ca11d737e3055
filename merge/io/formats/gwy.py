"""Gwyddion ``.gwy`` files: read any data field (own bounded reader of the serialisation),
write a mosaic (own writer, a block of rows at a time).

Gwyddion's data fields hold the top row first and its y grows down the rows: ``xoff``,
``yoff`` are the top-left corner of the field. The project's arrays hold the bottom row first
and its y grows up (rows along +y), so data flip vertically and y changes sign: the centre of
our pixel (0, 0), the bottom-left one, lies at ``(xoff + dx/2, -(yoff + yreal) + dy/2)``.
Tiles placed by their offsets in Gwyddion lie in the project's mosaic as Gwyddion shows them,
and a mosaic written here opens in Gwyddion where its input files lay.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from merge.io.formats.image import (
    AfmImage,
    FloatArray,
    FormatError,
    choose_channel,
    top_down_bands,
)

_SCALARS = {"b": "<?", "c": "<B", "i": "<i", "q": "<q", "d": "<d"}
_ARRAYS = {"C": "<u1", "I": "<i4", "Q": "<i8", "D": "<f8"}
GwyObject = tuple[str, dict[str, Any]]  # (type name, components)


class _Reader:
    """A bounded reader of Gwyddion's serialisation: every read checks the bytes are there,
    so a cut or corrupt file ends in a FormatError (gwyfile's reader can loop forever on one
    whose sizes were damaged)."""

    def __init__(self, data: bytes, path: Path) -> None:
        self.data, self.path = data, path

    def fail(self, what: str) -> FormatError:
        return FormatError(f"{self.path}: corrupt or cut Gwyddion file ({what})")

    def cstring(self, at: int, end: int) -> tuple[str, int]:
        stop = self.data.find(b"\0", at, end)
        if stop < 0:
            raise self.fail("an unterminated name")
        return self.data[at:stop].decode("utf-8", errors="replace"), stop + 1

    def unpack(self, fmt: str, at: int, end: int) -> tuple[Any, int]:
        size = struct.calcsize(fmt)
        if at + size > end:
            raise self.fail("a value runs past its object")
        return struct.unpack_from(fmt, self.data, at)[0], at + size

    def obj(self, at: int, end: int, depth: int = 0) -> tuple[GwyObject, int]:
        if depth > 32:
            raise self.fail("objects nested too deep")
        name, at = self.cstring(at, end)
        size, at = self.unpack("<I", at, end)
        stop = at + size
        if stop > end:
            raise self.fail(f"object {name!r} runs past the file")
        parts: dict[str, Any] = {}
        while at < stop:
            key, at = self.cstring(at, stop)
            kind, at = self.unpack("<c", at, stop)
            parts[key], at = self.value(kind.decode("latin-1"), at, stop, depth)
        return (name, parts), stop

    def value(self, kind: str, at: int, end: int, depth: int) -> tuple[Any, int]:
        if kind in _SCALARS:
            return self.unpack(_SCALARS[kind], at, end)
        if kind == "s":
            return self.cstring(at, end)
        if kind == "o":
            return self.obj(at, end, depth + 1)
        if kind in _ARRAYS or kind in "SO":
            count, at = self.unpack("<I", at, end)
            if kind in _ARRAYS:
                nbytes = count * np.dtype(_ARRAYS[kind]).itemsize
                if at + nbytes > end:
                    raise self.fail("an array runs past its object")
                arr = np.frombuffer(self.data, dtype=_ARRAYS[kind], count=count, offset=at)
                return arr, at + nbytes
            items = []
            for _ in range(count):
                item, at = self.cstring(at, end) if kind == "S" else self.obj(at, end, depth + 1)
                items.append(item)
            return items, at
        raise self.fail(f"unknown value type {kind!r}")


def _fields(path: Path) -> list[tuple[str, dict[str, Any]]]:
    """The data fields of a .gwy file as ``(title, components)``, in channel order."""
    data = path.read_bytes()
    if not data.startswith(b"GWYP"):
        raise FormatError(f"{path}: not a readable Gwyddion file (no GWYP header)")
    (_, top), _ = _Reader(data, path).obj(4, len(data))
    channels = sorted(int(m.group(1)) for k in top if (m := re.fullmatch(r"/(\d+)/data", k)))
    out: list[tuple[str, dict[str, Any]]] = []
    for n in channels:
        kind, field = top[f"/{n}/data"] if isinstance(top[f"/{n}/data"], tuple) else ("", {})
        if kind != "GwyDataField":
            continue
        title = top.get(f"/{n}/data/title")
        name = title if isinstance(title, str) and title else f"channel {n}"
        if any(name == other for other, _ in out):
            name = f"{name} ({n})"
        out.append((name, field))
    return out


def _unit(field: dict[str, Any], key: str) -> str:
    unit = field.get(key)
    if isinstance(unit, tuple) and isinstance(unit[1].get("unitstr"), str):
        return str(unit[1]["unitstr"])
    return ""


def read_gwy(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One data field of a ``.gwy`` file (topography by default, else the first in metres)."""
    p = Path(path)
    fields = _fields(p)
    names = [name for name, _ in fields]
    try:
        index = choose_channel(str(p), names, channel)
    except FormatError:
        metres = [i for i, (_, f) in enumerate(fields) if _unit(f, "si_unit_z") == "m"]
        if channel is not None or not metres:
            raise
        index = metres[0]
    field = fields[index][1]
    try:
        nx, ny = int(field["xres"]), int(field["yres"])
        xreal, yreal = float(field["xreal"]), float(field["yreal"])
        values = np.asarray(field["data"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise FormatError(f"{p}: data field {names[index]!r} lacks its size or data") from None
    if nx < 1 or ny < 1 or values.size != nx * ny or not (xreal > 0 and yreal > 0):
        raise FormatError(f"{p}: data field {names[index]!r} is inconsistent ({nx} x {ny})")
    dx, dy = xreal / nx, yreal / ny
    # Gwyddion's offset is the top-left corner, y down; ours the bottom-left pixel's centre
    # (Gwyddion leaves an offset of 0 out of the file: absent is 0, as Gwyddion reads it)
    xoff = float(field.get("xoff", 0.0) or 0.0) + dx / 2
    yoff = -(float(field.get("yoff", 0.0) or 0.0) + yreal) + dy / 2
    return AfmImage(
        heights=values.reshape(ny, nx)[::-1].copy(),
        pixel_size=(dx, dy),
        channel=names[index],
        unit=_unit(field, "si_unit_z") or "m",
        offset=(xoff, yoff),
        channels=tuple(names),
    )


#: Rows of a height map converted and written at a time (a few MB: a mosaic of any size is
#: written without a copy of it in memory).
BLOCK_BYTES = 8 << 20
#: Gwyddion's serialisation gives every object's size in 32 bits.
MAX_OBJECT = 2**32 - 1


def _name(key: str) -> bytes:
    return key.encode("utf-8") + b"\0"


def _scalar(key: str, code: str, value: Any) -> bytes:
    return _name(key) + code.encode() + struct.pack(_SCALARS[code], value)


def _text(key: str, value: str) -> bytes:
    return _name(key) + b"s" + _name(value)


def _object(name: str, body: bytes) -> bytes:
    return _name(name) + struct.pack("<I", len(body)) + body


def _si_unit(unit: str) -> bytes:
    return _object("GwySIUnit", _text("unitstr", unit))


class _Field:
    """A GwyDataField whose values are written block by block: ``head`` its serialisation up
    to its data, ``size`` that of the whole object (what Gwyddion reads as its length)."""

    def __init__(
        self, shape: tuple[int, int], pixel_size: tuple[float, float], origin: tuple[float, float]
    ) -> None:
        ny, nx = shape
        body = b"".join(
            [
                _scalar("xreal", "d", nx * pixel_size[0]),
                _scalar("yreal", "d", ny * pixel_size[1]),
                # the top-left corner, y down, as Gwyddion has it
                _scalar("xoff", "d", origin[0] - pixel_size[0] / 2),
                _scalar("yoff", "d", -(origin[1] - pixel_size[1] / 2 + ny * pixel_size[1])),
                _name("si_unit_xy") + b"o" + _si_unit("m"),
            ]
        )
        self.body, self.nx, self.ny = body, nx, ny

    def head(self, unit_z: str) -> bytes:
        body = b"".join(
            [
                self.body,
                _name("si_unit_z") + b"o" + _si_unit(unit_z),
                _scalar("xres", "i", self.nx),
                _scalar("yres", "i", self.ny),
                _name("data") + b"D" + struct.pack("<I", self.nx * self.ny),
            ]
        )
        size = len(body) + 8 * self.nx * self.ny  # within the container's, which is checked
        return _name("GwyDataField") + struct.pack("<I", size) + body


def write_gwy(
    path: str | Path,
    heights: FloatArray,
    *,
    pixel_size: tuple[float, float],
    origin: tuple[float, float] = (0.0, 0.0),
    title: str = "Height",
    metadata: dict[str, str] | None = None,
    channels: Sequence[tuple[str, FloatArray, str]] = (),
) -> None:
    """Write one height field (metres, rows along +y; any array, a memory-mapped one read a
    block of rows at a time) and string metadata, as Gwyddion opens it. Missing heights (NaN)
    are written as the lowest height and marked in the field's mask (1 = masked).
    ``channels``: more fields on the same grid, each ``(title, values, unit)`` (e.g. an SEM
    image resampled on the mosaic's grid), NaN written as their lowest value.

    The file is serialised here, not through gwyfile, which builds all of it in memory (five
    copies of a mosaic's heights); a field of more than 4 GB cannot be held by the format and
    is refused with a :class:`FormatError`.
    """
    h = np.asarray(heights)  # a memory map stays mapped
    if h.ndim != 2:
        raise FormatError(f"{path}: a .gwy field needs a 2-D map, got shape {h.shape}")
    ny, nx = h.shape
    blocks = top_down_bands(ny, nx, itemsize=8, budget=BLOCK_BYTES)
    low, holes = np.inf, False
    for lo, hi in blocks:
        block = np.asarray(h[lo:hi], dtype=np.float64)
        finite = np.isfinite(block)
        holes |= not finite.all()
        if finite.any():
            low = min(low, float(block[finite].min()))
    fill = low if np.isfinite(low) else 0.0
    field = _Field((ny, nx), pixel_size, origin)
    parts = [(_name("/0/data") + b"o", field.head("m"), "data")]
    parts.append((_text("/0/data/title", title), b"", ""))
    if holes:
        parts.append((_name("/0/mask") + b"o", field.head(""), "mask"))
    if metadata:
        meta = b"".join(_text(k, str(v)) for k, v in metadata.items())
        parts.append((_name("/0/meta") + b"o" + _object("GwyContainer", meta), b"", ""))
    extra: dict[str, tuple[FloatArray, float]] = {}
    for k, (name, values, unit) in enumerate(channels, start=1):
        v = np.asarray(values, dtype=np.float64)
        if v.shape != h.shape:
            raise FormatError(f"{path}: channel {name!r} is {v.shape}, the heights {h.shape}")
        finite = np.isfinite(v)
        extra[f"extra{k}"] = (v, float(v[finite].min()) if finite.any() else 0.0)
        parts.append((_name(f"/{k}/data") + b"o", field.head(unit), f"extra{k}"))
        parts.append((_text(f"/{k}/data/title", name), b"", ""))
    size = sum(len(a) + len(b) + (8 * nx * ny if kind else 0) for a, b, kind in parts)
    if size > MAX_OBJECT:
        raise FormatError(
            f"{nx} x {ny} heights are more than a .gwy file can hold (4 GB); export them as "
            ".tif (BigTIFF) or .npy"
        )
    with Path(path).open("wb") as out:
        out.write(b"GWYP" + _name("GwyContainer") + struct.pack("<I", size))
        for key, head, kind in parts:
            out.write(key + head)
            for lo, hi in blocks if kind else ():
                if kind in extra:
                    more, lowest = extra[kind]
                    block = more[lo:hi][::-1]
                    values = np.where(np.isfinite(block), block, lowest)
                    out.write(np.ascontiguousarray(values, dtype="<f8").tobytes())
                    continue
                block = np.asarray(h[lo:hi], dtype=np.float64)[::-1]
                if kind == "data":
                    values = np.where(np.isfinite(block), block, fill)
                else:
                    values = (~np.isfinite(block)).astype(np.float64)
                out.write(np.ascontiguousarray(values, dtype="<f8").tobytes())
