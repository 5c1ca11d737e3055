"""Asylum Research ``.ibw``: an Igor binary wave holding every channel of a scan.

The wave (read with igor2) is ``data[x, y, layer]``: x the fast axis, y the slow one, one
layer per channel, named by the labels of dimension 2 (``HeightRetrace``,
``AmplitudeRetrace`` ...). The wave's own scaling gives the pixel pitch (``sfA``) and the
position of element 0 (``sfB``), which is where Igor and Asylum's software place it. Rows of
the image are ``data[:, :, k].T`` with y growing with the row, this project's orientation;
Gwyddion shows ``rot90`` of the layer, the same image top row first.
"""

from __future__ import annotations

import contextlib
import io
import struct
from pathlib import Path
from typing import Any

import numpy as np

from merge.io.formats.image import AfmImage, FormatError, choose_channel

#: Bytes per value of Igor's numeric wave types (TN003: NT_FP32 2, NT_FP64 4, NT_I8 8,
#: NT_I16 0x10, NT_I32 0x20, unsigned with 0x40, complex with 0x01).
_REAL = {2: 4, 4: 8, 8: 1, 0x10: 2, 0x20: 4}
_ITEM_SIZE = {
    **_REAL,
    **{t | 0x40: n for t, n in _REAL.items() if t >= 8},
    **{t | 0x01: 2 * n for t, n in _REAL.items()},
}


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        return value.decode("latin-1").rstrip("\0")
    if isinstance(value, np.ndarray):
        return value.tobytes().decode("latin-1").rstrip("\0")
    return str(value)


def _check_sizes(path: Path, head: bytes, size: int) -> None:
    """Refuse a version 5 header whose sections cannot fit the file, before igor2 reads it
    (it would try to read, and then walk, whatever sizes a corrupt header claims)."""
    if len(head) < 64 + 320:
        raise FormatError(f"{path}: truncated: the Igor headers need 384 bytes")
    order = "<" if head[:2] == b"\x05\x00" else ">"
    sections = struct.unpack_from(order + "14l", head, 4)  # wfmSize ... sIndicesSize
    npnts, wave_type = struct.unpack_from(order + "lh", head, 64 + 12)
    n_dim = struct.unpack_from(order + "4l", head, 64 + 68)
    if min(sections) < 0 or 64 + sum(sections) > size:
        raise FormatError(
            f"{path}: truncated or corrupt: its header claims more than the file holds"
        )
    dims = [d for d in n_dim if d != 0]
    if npnts < 0 or min(n_dim) < 0 or (dims and int(np.prod(dims)) != npnts):
        raise FormatError(f"{path}: corrupt: {npnts} points do not fill dimensions {n_dim}")
    if wave_type not in _ITEM_SIZE or sections[0] < 320 + npnts * _ITEM_SIZE[wave_type]:
        raise FormatError(f"{path}: corrupt or not numeric: wave type {wave_type}")


def _load(path: Path) -> dict[str, Any]:
    from igor2 import binarywave

    with path.open("rb") as f:
        head = f.read(384)
    _check_sizes(path, head, path.stat().st_size)
    # A parser of its own for every file: igor2.load reuses one per thread, and a corrupt
    # file leaves it in a state that makes every later load slower (minutes after a few
    # dozen bad uploads). igor2 also prints its parse errors, raw bytes and all, to stdout.
    parser = binarywave.setup_wave(byte_order="=")
    try:
        with path.open("rb") as f, contextlib.redirect_stdout(io.StringIO()):
            wave: dict[str, Any] = parser.unpack_stream(f)["wave"]
    except Exception as exc:  # igor2 raises anything from struct.error to AssertionError
        raise FormatError(f"{path}: not a readable Igor binary wave ({exc!r:.200})") from None
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
