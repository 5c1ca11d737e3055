"""Nanosurf ``.nid``: an INI-style text header, ``#!``, then the channels as binary integers.

Written from the header's own description (no vendor package): ``[DataSet]`` lists the
channels group by group (``Gr0-Ch1=DataSet-0:1``), each channel section gives ``Points``,
``Lines``, the X/Y ranges and the Z range and minimum that map the integers to values, and
the binary block holds the channels in that order. Row 0 is the first line stored, which is
how the shipped ``mos2.npy`` holds it (Gwyddion shows the same data flipped vertically).

Where the scan lies: ``[DataSet\\Parameters\\Imaging]`` gives ``ScanOffset=V[x,y,z]*[m,m,m]``,
the centre of the scan area (the channels' own ``Dim0Min``/``Dim1Min`` are 0, the image's own
frame), and ``[DataSet-Info]`` its rotation in the scan plane (``Rotation=45 °``), kept in the
metadata as ``rotation_deg``: a rotated scan is not placed by its offset alone.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from merge.io.formats.image import AfmImage, FormatError, choose_channel

_DTYPES = {(16, "Signed"): "<i2", (32, "Signed"): "<i4", (16, "Unsigned"): "<u2",
           (32, "Unsigned"): "<u4", (64, "Signed"): "<i8"}  # fmt: skip


def _sections(text: str) -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            current = out.setdefault(line[1:-1], {})
        elif current is not None and "=" in line:
            key, value = line.split("=", 1)
            current[key.strip()] = value.strip()
    return out


def _vector(text: str | None) -> list[float] | None:
    """``V[1.2e-06,-3e-07,0]*[m,m,m]`` as numbers (None when absent or not one)."""
    match = re.fullmatch(r"V\[([^\]]*)\]\*\[[^\]]*\]", (text or "").strip())
    if match is None:
        return None
    try:
        return [float(v) for v in match.group(1).split(",")]
    except ValueError:
        return None


def _degrees(text: str | None) -> float:
    """``45 °`` (or ``-175m°``) in degrees; 0 when absent."""
    match = re.match(r"\s*([-+0-9.eE]+)\s*(m?)", text or "")
    if match is None:
        return 0.0
    value = float(match.group(1))
    return value / 1000 if match.group(2) else value


def read_nid(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One channel of a Nanosurf ``.nid`` file (topography by default), SI units."""
    p = Path(path)
    data = p.read_bytes()
    split = data.find(b"#!")
    if split < 0 or not data.startswith(b"[DataSet]"):
        raise FormatError(f"{p}: not a Nanosurf .nid file (no [DataSet] header and #! marker)")
    sections = _sections(data[:split].decode("latin-1"))
    groups = sections.get("DataSet", {})
    refs: list[tuple[str, str]] = []  # (channel name, section)
    n_groups = int(groups.get("GroupCount", "0") or 0)
    for g in range(n_groups):
        frame = groups.get(f"Gr{g}-Name", f"group {g}")
        keys = sorted(
            (int(m.group(1)), v)
            for k, v in groups.items()
            if (m := re.fullmatch(rf"Gr{g}-Ch(\d+)", k))
        )
        for _, section in keys:
            info = sections.get(section)
            if info is None:
                raise FormatError(f"{p}: the header names {section} but has no such section")
            direction = frame.replace("Scan ", "").strip() or frame
            refs.append((f"{info.get('Dim2Name', section)} {direction}", section))
    names = [name for name, _ in refs]
    index = choose_channel(str(p), names, channel)
    offset = split + 2
    for k, (name, section) in enumerate(refs):
        info = sections[section]
        try:
            nx, ny = int(info["Points"]), int(info["Lines"])
            bits, sign = int(info.get("SaveBits", "32")), info.get("SaveSign", "Signed")
            dtype = np.dtype(_DTYPES[(bits, sign)])
        except (KeyError, ValueError):
            raise FormatError(f"{p}: channel {name!r} has an unreadable layout") from None
        size = nx * ny * dtype.itemsize
        if k == index:
            if offset + size > len(data):
                raise FormatError(f"{p}: truncated: channel {name!r} needs {size} bytes")
            raw = np.frombuffer(data, dtype=dtype, count=nx * ny, offset=offset).reshape(ny, nx)
            zrange, zmin = float(info["Dim2Range"]), float(info["Dim2Min"])
            full = 2.0**bits
            shift = 2.0 ** (bits - 1) if sign == "Signed" else 0.0
            heights = zmin + (raw.astype(np.float64) + shift) / full * zrange
            width, height = float(info["Dim0Range"]), float(info["Dim1Range"])
            dx, dy = width / nx, height / ny
            centre = _vector(sections.get("DataSet\\Parameters\\Imaging", {}).get("ScanOffset"))
            place: tuple[float, float] | None = None
            if centre is not None and len(centre) >= 2:
                place = (centre[0] - width / 2 + dx / 2, centre[1] - height / 2 + dy / 2)
            rotation = _degrees(sections.get("DataSet-Info", {}).get("Rotation"))
            return AfmImage(
                heights=heights,
                pixel_size=(dx, dy),
                channel=name,
                unit=info.get("Dim2Unit", ""),
                offset=place,
                channels=tuple(names),
                metadata={"rotation_deg": f"{rotation:g}"},
            )
        offset += size
    raise FormatError(f"{p}: channel {names[index]!r} not found in the data block")
