"""Gwyddion ``.gwy`` files: read any data field (own bounded reader of the serialisation),
write a mosaic (gwyfile, MIT).

Gwyddion's data fields hold the top row first; the project's arrays hold the bottom row
first (rows along +y), so both directions flip vertically. Gwyddion's offset is the field's
corner, ours the centre of pixel (0, 0): half a pixel apart, converted both ways.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path
from typing import Any

import numpy as np

from backend.formats.image import AfmImage, FloatArray, FormatError, choose_channel

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
    # Gwyddion's offset is the field's corner; ours is pixel (0, 0)'s centre
    xoff = float(field.get("xoff", 0.0) or 0.0) + dx / 2
    yoff = float(field.get("yoff", 0.0) or 0.0) + dy / 2
    return AfmImage(
        heights=values.reshape(ny, nx)[::-1].copy(),
        pixel_size=(dx, dy),
        channel=names[index],
        unit=_unit(field, "si_unit_z") or "m",
        offset=(xoff, yoff),
        channels=tuple(names),
    )


def write_gwy(
    path: str | Path,
    heights: FloatArray,
    *,
    pixel_size: tuple[float, float],
    origin: tuple[float, float] = (0.0, 0.0),
    title: str = "Height",
    metadata: dict[str, str] | None = None,
    mask: FloatArray | None = None,
) -> None:
    """Write one height field (metres, rows along +y) with an optional mask (1 = masked) and
    string metadata, as Gwyddion opens it."""
    from gwyfile.objects import GwyContainer, GwyDataField, GwySIUnit

    h = np.asarray(heights, dtype=np.float64)
    ny, nx = h.shape

    def field(values: FloatArray, unit_z: str) -> Any:
        return GwyDataField(
            np.ascontiguousarray(values[::-1]),
            xreal=nx * pixel_size[0],
            yreal=ny * pixel_size[1],
            xoff=origin[0] - pixel_size[0] / 2,  # the corner, as Gwyddion has it
            yoff=origin[1] - pixel_size[1] / 2,
            si_unit_xy=GwySIUnit(unitstr="m"),
            si_unit_z=GwySIUnit(unitstr=unit_z),
        )

    container = GwyContainer()
    container["/0/data"] = field(
        np.nan_to_num(h, nan=float(np.nanmin(h)) if np.isfinite(h).any() else 0.0), "m"
    )
    container["/0/data/title"] = title
    if mask is not None:
        container["/0/mask"] = field(np.asarray(mask, dtype=np.float64), "")
    if metadata:
        meta = GwyContainer()
        for key, value in metadata.items():
            meta[key] = str(value)
        container["/0/meta"] = meta
    container.tofile(str(path))
