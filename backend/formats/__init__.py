"""AFM file formats at the edge: readers that return SI heights, writers of a merged mosaic.

Readers by suffix (:data:`READERS`, :func:`reader_for`): Nanosurf ``.nid``, Gwyddion ``.gwy``,
Bruker NanoScope ``.spm`` and its numbered captures (``.000`` ...), Asylum ``.ibw``, Nanonis
``.sxm``, Park Systems and plain TIFF, ``.npy``.
Every reader returns an :class:`AfmImage` with rows along +y (see :mod:`.image`).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from backend.formats.exports import EXPORTS, export_heights
from backend.formats.gwy import read_gwy
from backend.formats.ibw import read_ibw
from backend.formats.image import AfmImage, FormatError
from backend.formats.nanoscope import read_nanoscope
from backend.formats.nid import read_nid
from backend.formats.sxm import read_sxm
from backend.formats.tiff import read_tiff


def read_npy(
    path: str | Path, *, channel: str | None = None, pixel_size: tuple[float, float] | None = None
) -> AfmImage:
    p = Path(path)
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
            return reader(p, channel=channel, pixel_size=pixel_size)
        return reader(p, channel=channel)
    except FormatError:
        raise
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
