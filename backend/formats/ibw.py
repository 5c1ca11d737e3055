"""Asylum Research ``.ibw``: an Igor binary wave holding every channel of a scan.

The wave (read with igor2) is ``data[x, y, layer]``: x the fast axis, y the slow one, one
layer per channel, named by the labels of dimension 2 (``HeightRetrace``,
``AmplitudeRetrace`` ...). The wave's own scaling gives the pixel pitch (``sfA``) and the
position of element 0 (``sfB``), which is where Igor and Asylum's software place it. Rows of
the image are ``data[:, :, k].T`` with y growing with the row, this project's orientation;
Gwyddion shows ``rot90`` of the layer, the same image top row first.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from backend.formats.image import AfmImage, FormatError, choose_channel


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("latin-1").rstrip("\0")
    if isinstance(value, np.ndarray):
        return value.tobytes().decode("latin-1").rstrip("\0")
    return str(value)


def _load(path: Path) -> dict[str, Any]:
    from igor2 import binarywave

    try:
        wave: dict[str, Any] = binarywave.load(str(path))["wave"]
    except Exception as exc:  # igor2 raises anything from struct.error to AssertionError
        raise FormatError(f"{path}: not a readable Igor binary wave ({exc!r})") from None
    return wave


def read_ibw(path: str | Path, *, channel: str | None = None) -> AfmImage:
    """One channel of an Asylum ``.ibw`` scan (the height by default), SI units."""
    p = Path(path)
    with p.open("rb") as f:
        version = f.read(2)
    if version not in (b"\x05\x00", b"\x00\x05"):
        raise FormatError(f"{p}: not an Igor binary wave of version 5 (Asylum scans are)")
    wave = _load(p)
    data = np.asarray(wave["wData"])
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim != 3 or min(data.shape[:2]) < 2:
        raise FormatError(f"{p}: holds no image (wave of shape {data.shape})")
    header = wave["wave_header"]
    labels = wave.get("labels") or []
    layer_labels = [_text(s) for s in labels[2][1:]] if len(labels) > 2 and labels[2] else []
    wave_name = _text(header["bname"]) or "wave"
    names = [
        layer_labels[k] if k < len(layer_labels) and layer_labels[k] else f"{wave_name} {k}"
        for k in range(data.shape[2])
    ]
    unit = _text(header["dataUnits"]) or "m"
    if len(names) == 1 and channel is None and unit == "m":
        index = 0  # one unnamed layer of lengths: a height image (a processed wave)
    else:
        index = choose_channel(str(p), names, channel)
    dx, dy = (float(v) for v in header["sfA"][:2])
    x0, y0 = (float(v) for v in header["sfB"][:2])
    if not (np.isfinite(dx) and np.isfinite(dy) and dx > 0 and dy > 0):
        raise FormatError(f"{p}: the wave's x/y scaling ({dx}, {dy}) is not a pixel size")
    if names[index].lower().startswith("phase"):
        unit = "deg"  # Asylum keeps phase in degrees under the wave's length unit
    return AfmImage(
        heights=np.asarray(data[:, :, index].T, dtype=np.float64),
        pixel_size=(dx, dy),
        channel=names[index],
        unit=unit,
        offset=(x0, y0),
        channels=tuple(names),
        metadata=_note(wave.get("note", b"")),
    )


def _note(raw: Any) -> dict[str, str]:
    """Asylum's wave note: ``Key: value`` lines separated by carriage returns."""
    out: dict[str, str] = {}
    for line in _text(raw).replace("\r", "\n").splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip():
            out[key.strip()] = value.strip()
    return out
