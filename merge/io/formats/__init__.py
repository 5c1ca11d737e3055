"""AFM file formats at the edge: readers that return SI heights, writers of a merged mosaic.

Readers by suffix (:data:`READERS`, :func:`reader_for`): Nanosurf ``.nid``, Gwyddion ``.gwy``,
Bruker NanoScope ``.spm`` and its numbered captures (``.000`` ...), Asylum ``.ibw``, Nanonis
``.sxm``, Park Systems and plain TIFF, ``.npy``.
Every reader returns an :class:`AfmImage` with rows along +y (see :mod:`.image`).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from merge.io.formats.exports import EXPORTS, export_heights
from merge.io.formats.gwy import read_gwy
from merge.io.formats.ibw import read_ibw
from merge.io.formats.image import AfmImage, FormatError
from merge.io.formats.nanoscope import read_nanoscope
from merge.io.formats.nid import read_nid
from merge.io.formats.sxm import read_sxm
from merge.io.formats.tiff import read_tiff

#: Most pixels one scan may have (4096 x 4096): larger ones are refused before they are read.
MAX_PIXELS = 4096 * 4096


def _check_pixels(p: Path, shape: tuple[int, ...]) -> None:
    if math.prod(shape) > MAX_PIXELS:
        raise FormatError(
            f"{p}: {' x '.join(map(str, shape))} pixels is more than the {MAX_PIXELS} a scan "
            "may have"
        )


def _npy_header(p: Path) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """A ``.npy`` file's shape and dtype from its header, checked against the file's size
    before anything is allocated (a 218-byte file may claim 60000 x 60000)."""
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            header = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = header(f)
            offset = f.tell()
    except (OSError, ValueError) as exc:
        raise FormatError(f"{p}: not a readable .npy array ({exc})") from None
    if dtype.hasobject:
        raise FormatError(f"{p}: a .npy of Python objects is not a height array")
    _check_pixels(p, shape)
    expected = offset + math.prod(shape) * dtype.itemsize
    actual = p.stat().st_size
    if actual != expected:
        raise FormatError(
            f"{p}: its header claims {shape} of {dtype} ({expected} bytes) but the file has "
            f"{actual} bytes: truncated or damaged"
        )
    return shape, dtype


def read_npy(
    path: str | Path, *, channel: str | None = None, pixel_size: tuple[float, float] | None = None
) -> AfmImage:
    p = Path(path)
    _npy_header(p)
    try:
        data = np.load(p, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{p}: not a readable .npy array ({exc})") from None
    if data.ndim != 2:
        raise FormatError(f"{p}: need a 2-D height array, got shape {data.shape}")
    size = pixel_size
    side = p.with_suffix(".json")
    if size is None and side.exists():
        import json

        try:
            dx, dy = json.loads(side.read_text(encoding="utf-8"))["pixel_size"]
            size = (float(dx), float(dy))
        except (ValueError, KeyError, TypeError):  # an unrelated .json: ask for the size
            size = None
    if size is None:
        raise FormatError(f"{p}: a .npy has no pixel size: give it (metres) or a .json beside it")
    return AfmImage(
        np.asarray(data, dtype=np.float64), (float(size[0]), float(size[1])), channel or "heights"
    )


Reader = Callable[..., AfmImage]
READERS: dict[str, Reader] = {
    ".nid": read_nid,
    ".gwy": read_gwy,
    ".spm": read_nanoscope,
    ".ibw": read_ibw,
    ".sxm": read_sxm,
    ".tif": read_tiff,
    ".tiff": read_tiff,
    ".npy": read_npy,
}


#: What :func:`reader_for` accepts, for messages.
READABLE = ", ".join([*READERS, ".000-.999"])


def reader_for(path: str | Path) -> Reader | None:
    """The reader of ``path`` by its suffix (NanoScope numbers its files ``.000``, ``.001`` ...)."""
    suffix = Path(path).suffix.lower()
    if len(suffix) == 4 and suffix[1:].isdigit():
        return read_nanoscope
    return READERS.get(suffix)


def read_image(
    path: str | Path, *, channel: str | None = None, pixel_size: tuple[float, float] | None = None
) -> AfmImage:
    """Read ``path`` by its suffix; ``pixel_size`` for formats that do not carry one."""
    p = Path(path)
    reader = reader_for(p)
    if reader is None:
        raise FormatError(f"{p}: unknown AFM format {p.suffix!r}; readable: {READABLE}")
    if not p.is_file():
        raise FormatError(f"{p}: no such file")
    try:
        if reader in (read_tiff, read_npy):
            image = reader(p, channel=channel, pixel_size=pixel_size)
        else:
            image = reader(p, channel=channel)
        _check_pixels(p, image.heights.shape)
        return image
    except FormatError:
        raise
    except MemoryError:
        raise FormatError(f"{p}: declares more data than this server can hold") from None
    except (ValueError, KeyError, IndexError, AttributeError, TypeError, ArithmeticError,
            struct.error, EOFError) as exc:  # fmt: skip
        # a header field the reader did not expect to be broken: the file's fault, said so
        raise FormatError(
            f"{p}: corrupt or unsupported {p.suffix} file ({type(exc).__name__}: {exc})"[:500]
        ) from None


__all__ = [
    "EXPORTS",
    "READABLE",
    "READERS",
    "AfmImage",
    "FormatError",
    "export_heights",
    "read_image",
    "reader_for",
]
