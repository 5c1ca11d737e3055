"""Gwyddion ``.gwy`` files through gwyfile (MIT): read any data field, write a mosaic.

Gwyddion's data fields hold the top row first; the project's arrays hold the bottom row
first (rows along +y), so both directions flip vertically. Gwyddion's offset is the field's
corner, ours the centre of pixel (0, 0): half a pixel apart, converted both ways.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from backend.formats.image import AfmImage, FloatArray, FormatError, choose_channel


def _unit(field: Any, key: str) -> str:
    unit = field.get(key)
    return str(unit.get("unitstr", "")) if unit is not None else ""


def read_gwy(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One data field of a ``.gwy`` file (topography by default, else the first in metres)."""
    import gwyfile
    from gwyfile.util import get_datafields

    p = Path(path)
    try:
        fields = get_datafields(gwyfile.load(str(p)))
    except Exception as exc:  # gwyfile raises plain exceptions on foreign or cut files
        raise FormatError(f"{p}: not a readable Gwyddion file ({exc})") from None
    names = list(fields)
    try:
        index = choose_channel(str(p), names, channel)
    except FormatError:
        metres = [i for i, n in enumerate(names) if _unit(fields[n], "si_unit_z") == "m"]
        if channel is not None or not metres:
            raise
        index = metres[0]
    field = fields[names[index]]
    data = np.asarray(field.data, dtype=np.float64)
    ny, nx = data.shape
    dx, dy = float(field.xreal) / nx, float(field.yreal) / ny
    # Gwyddion's offset is the field's corner; ours is pixel (0, 0)'s centre
    xoff = float(field.get("xoff", 0.0) or 0.0) + dx / 2
    yoff = float(field.get("yoff", 0.0) or 0.0) + dy / 2
    return AfmImage(
        heights=data[::-1].copy(),
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
