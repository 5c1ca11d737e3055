"""Park Systems (PSIA) ``.tiff``: an ordinary TIFF preview whose private tags hold the scan.

Tags 50432 (magic ``0x0E031301``), 50433 (version 1 or 2), 50434 (the data, line by line,
little endian) and 50435 (a binary header, little endian: channel name, resolution, scan
size and offset in µm, and the value scaling). Version 1 data are 16-bit integers; version 2
appends fields whose ``data type`` says int16, int32 or float32. A value is
``gain * (scale * raw + offset)`` in the header's Z unit (a scale of 0 means 1; no unit means
µm); the gain may be negative and is applied as it stands.

The first line stored is the bottom of the image (Gwyddion shows it flipped), this project's
row 0. The header's X/Y offset is the centre of the scan; it becomes the offset of pixel
(0, 0). Read with tifffile; the layout follows Gwyddion's import, which the tests check.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

from merge.io.formats.image import AfmImage, FormatError, choose_channel

MAGIC = 0x0E031301
TAG_MAGIC, TAG_VERSION, TAG_DATA, TAG_HEADER = 50432, 50433, 50434, 50435
VERSIONS = (0x01000001, 0x01000002)
_DTYPES = {0: "<i2", 1: "<i4", 2: "<f4"}
_LENGTH = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "pm": 1e-12, "Å": 1e-10}

# (name, struct code) of the version 1 header; "U<n>" is UTF-16 text of n characters
_HEADER_V1 = [
    ("image_type", "I"), ("source_name", "U32"), ("image_mode", "U8"), ("lpf_strength", "d"),
    ("auto_flatten", "I"), ("ac_track", "I"), ("xres", "I"), ("yres", "I"), ("angle", "d"),
    ("sine_scan", "I"), ("overscan_rate", "d"), ("forward", "I"), ("scan_up", "I"),
    ("swap_xy", "I"), ("xreal_um", "d"), ("yreal_um", "d"), ("xoff_um", "d"), ("yoff_um", "d"),
    ("scan_rate", "d"), ("set_point", "d"), ("set_point_unit", "U8"), ("tip_bias", "d"),
    ("sample_bias", "d"), ("data_gain", "d"), ("z_scale", "d"), ("z_offset", "d"),
    ("z_unit", "U8"), ("data_min", "i"), ("data_max", "i"), ("data_avg", "i"),
    ("compression", "I"), ("log_scale", "I"), ("square", "I"),
]  # fmt: skip
_HEADER_V2 = [
    ("servo_gain", "d"), ("scanner_range", "d"), ("xy_voltage_mode", "U8"),
    ("z_voltage_mode", "U8"), ("xy_servo_mode", "U8"), ("data_type", "I"), ("reserved1", "I"),
    ("reserved2", "I"), ("ncm_amplitude", "d"), ("ncm_frequency", "d"), ("cantilever", "U16"),
]  # fmt: skip


def is_park(tags: Any) -> bool:
    """Whether a TIFF page's tags carry the Park magic number."""
    magic = tags.get(TAG_MAGIC)
    return magic is not None and magic.value == MAGIC


def _field_size(code: str) -> int:
    """Bytes of one header field: ``U<n>`` is n UTF-16 characters, else a struct code."""
    return 2 * int(code[1:]) if code.startswith("U") else struct.calcsize("<" + code)


def _unpack(fields: list[tuple[str, str]], raw: bytes, at: int) -> tuple[dict[str, Any], int]:
    out: dict[str, Any] = {}
    for name, code in fields:
        size = _field_size(code)
        if code.startswith("U"):
            text = raw[at : at + size].decode("utf-16-le", errors="replace")
            out[name] = text.split("\0", 1)[0].strip()
        else:
            out[name] = struct.unpack_from("<" + code, raw, at)[0]
        at += size
    return out, at


def _header(raw: bytes, version: int, path: Path) -> dict[str, Any]:
    fields = _HEADER_V1 + (_HEADER_V2 if version == VERSIONS[1] else [])
    need = sum(_field_size(code) for _, code in fields)
    if len(raw) < need:
        raise FormatError(f"{path}: the Park header holds {len(raw)} bytes, needs {need}")
    header, at = _unpack(_HEADER_V1, raw, 0)
    header["data_type"] = 0
    if version == VERSIONS[1]:
        header.update(_unpack(_HEADER_V2, raw, at)[0])
    return header


def read_park(tags: Any, path: Path, *, channel: str | None = None) -> AfmImage:
    """The scan of a Park TIFF page (its tags as tifffile gives them), SI units."""
    version = tags.get(TAG_VERSION)
    if version is None or version.value not in VERSIONS:
        found = "none" if version is None else hex(version.value)
        raise FormatError(f"{path}: unsupported Park TIFF version {found} (1 and 2 are read)")
    header_tag, data_tag = tags.get(TAG_HEADER), tags.get(TAG_DATA)
    if header_tag is None or data_tag is None:
        raise FormatError(f"{path}: a Park TIFF without its header or data tag")
    header = _header(bytes(header_tag.value), version.value, path)
    if header["image_type"] != 0:
        raise FormatError(f"{path}: a Park line profile or spectrum, not an image")
    nx, ny = int(header["xres"]), int(header["yres"])
    dtype = _DTYPES.get(int(header["data_type"]))
    if dtype is None:
        raise FormatError(f"{path}: unknown Park data type {header['data_type']}")
    raw = bytes(data_tag.value)
    size = nx * ny * np.dtype(dtype).itemsize
    if nx < 1 or ny < 1 or len(raw) < size:
        raise FormatError(f"{path}: truncated: {len(raw)} data bytes for {nx} x {ny} pixels")
    name = header["source_name"] or "image"
    choose_channel(str(path), [name], channel)  # one channel per file: names the wrong ask
    scale = header["z_scale"] or 1.0
    counts = np.frombuffer(raw, dtype=dtype, count=nx * ny).reshape(ny, nx).astype(np.float64)
    values = header["data_gain"] * (scale * counts + header["z_offset"])
    unit = header["z_unit"] or "um"
    if unit in _LENGTH:
        values, unit = values * _LENGTH[unit], "m"
    width, height = header["xreal_um"] * 1e-6, header["yreal_um"] * 1e-6
    dx, dy = width / nx, height / ny
    if not (dx > 0 and dy > 0):
        raise FormatError(f"{path}: the Park header gives no scan size ({width} x {height} m)")
    cx, cy = header["xoff_um"] * 1e-6, header["yoff_um"] * 1e-6
    return AfmImage(
        heights=values,
        pixel_size=(dx, dy),
        channel=name,
        unit=unit,
        offset=(cx - width / 2 + dx / 2, cy - height / 2 + dy / 2),
        channels=(name,),
        metadata={k: str(v) for k, v in header.items()},
    )
