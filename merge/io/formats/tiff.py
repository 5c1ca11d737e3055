"""TIFF height maps: 32-bit float with the pixel size in the resolution tags (written), and
plain TIFF images read with a given pixel size (or the one in the tags, when in cm). Park
Systems TIFFs, recognised by their private tags, go to :mod:`.park`.

A TIFF's first row is the top of the image (as Gwyddion shows it): rows are flipped to the
project's rows-along-+y on the way in and out.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from merge.io.formats.image import AfmImage, FloatArray, FormatError, top_down_bands
from merge.io.formats.park import is_park, read_park

#: Bytes of heights from which a TIFF is written as BigTIFF: a classic TIFF's offsets are 32
#: bits, so a file past 4 GB (a mosaic of 32,000 x 32,000 px in float32) cannot be one; below,
#: classic TIFF, which every reader opens.
BIGTIFF_FROM = (1 << 32) - (1 << 26)


#: Values a TIFF scan may declare (RGB counts three a pixel): a 4096 x 4096 scan's.
MAX_DECODED = 3 * 4096 * 4096

#: Bytes of float32 heights per strip: a mosaic is converted and written a strip at a time.
STRIP_BYTES = 4 << 20


def write_tiff(
    path: str | Path,
    heights: FloatArray,
    *,
    pixel_size: tuple[float, float],
    pages: Sequence[tuple[str, FloatArray]] = (),
) -> None:
    """Float32 heights in metres; X/YResolution in pixels per centimetre (so the size is
    there for any reader), and the exact pitch in the description; BigTIFF from
    :data:`BIGTIFF_FROM` bytes of heights. Written in strips of :data:`STRIP_BYTES`, top row
    first, each converted as it goes: a memory-mapped mosaic is never copied whole.
    ``pages``: more pages on the same grid after the heights, each ``(name, values)`` (e.g.
    an SEM image resampled on the mosaic's grid), float32, their name in the description."""
    import tifffile

    h = np.asarray(heights)  # a memory map stays mapped
    if h.ndim != 2:
        raise FormatError(f"{path}: a TIFF export needs a 2-D map, got shape {h.shape}")
    ny, nx = h.shape
    bands = top_down_bands(ny, nx, itemsize=4, budget=STRIP_BYTES)
    rows = bands[0][1] - bands[0][0] if bands else 1

    def strips() -> Iterator[bytes]:
        for lo, hi in bands:
            yield np.asarray(h[lo:hi][::-1], dtype="<f4").tobytes()

    resolution = (1e-2 / pixel_size[0], 1e-2 / pixel_size[1])
    pitch = f"pixel_size {pixel_size[0]!r} {pixel_size[1]!r}"
    with tifffile.TiffWriter(
        str(path), bigtiff=4 * ny * nx * (1 + len(pages)) >= BIGTIFF_FROM
    ) as tif:
        tif.write(
            strips(),
            shape=(ny, nx),
            dtype="<f4",
            rowsperstrip=rows,
            resolution=resolution,
            resolutionunit="CENTIMETER",
            description=f"mosaic-afm heights m {pitch}",
            metadata=None,
        )
        for name, values in pages:
            v = np.asarray(values)
            if v.shape != (ny, nx):
                raise FormatError(f"{path}: page {name!r} is {v.shape}, the heights {(ny, nx)}")
            tif.write(
                np.ascontiguousarray(v[::-1], dtype="<f4"),
                resolution=resolution,
                resolutionunit="CENTIMETER",
                description=f"mosaic-afm {name} {pitch}",
                metadata=None,
            )


def check_declared(page: Any, name: str, *, limit: int) -> None:
    """Refuse a TIFF page whose declared size is past ``limit`` pixels, from its header alone:
    a compressed page of a few kilobytes may unpack to gigabytes (a decompression bomb)."""
    shape = tuple(int(n) for n in page.shape)
    if math.prod(shape) > limit or page.dtype is None:
        size = " x ".join(map(str, shape))
        raise FormatError(
            f"{name}: the TIFF declares {size} values, more than the {limit} this server "
            "decodes: crop or bin the image first"
        )


def read_tiff(
    path: str | Path, *, channel: str | None = None, pixel_size: tuple[float, float] | None = None
) -> AfmImage:
    """A single-channel TIFF as heights. Float data are taken as metres; integer data as
    grey levels (unit "counts"). The pixel size: given, else ours, else the resolution tags.
    A Park Systems TIFF is read from its own tags, with its own scaling."""
    import tifffile

    p = Path(path)
    try:
        with tifffile.TiffFile(str(p)) as tif:
            page = tif.pages.first
            if is_park(page.tags):
                return read_park(page.tags, p, channel=channel)
            check_declared(page, str(p), limit=MAX_DECODED)
            data = np.asarray(page.asarray(), dtype=np.float64)
            description = page.description or ""
            tags = page.tags
            xres, yres = tags.get("XResolution"), tags.get("YResolution")
            unit = tags.get("ResolutionUnit")
            floating = page.dtype is not None and page.dtype.kind == "f"
    except FormatError:
        raise
    except Exception as exc:  # tifffile raises many kinds on foreign or cut files
        raise FormatError(f"{p}: not a readable TIFF ({type(exc).__name__}: {exc})") from None
    if data.ndim != 2:
        raise FormatError(f"{p}: need one 2-D channel, got an image of shape {data.shape}")
    size = pixel_size
    if size is None and description.startswith("mosaic-afm heights"):
        parts = description.split()
        size = (float(parts[-2]), float(parts[-1]))
    if size is None and xres is not None and yres is not None and unit is not None:
        per = {2: 2.54e-2, 3: 1e-2}.get(int(unit.value))
        if per is not None:
            size = (per * xres.value[1] / xres.value[0], per * yres.value[1] / yres.value[0])
    if size is None or not all(np.isfinite(size)) or min(size) <= 0:
        raise FormatError(f"{p}: the TIFF says no pixel size: give it (metres)")
    return AfmImage(
        heights=data[::-1].copy(),
        pixel_size=(float(size[0]), float(size[1])),
        channel=channel or "image",
        unit="m" if floating else "counts",
        channels=("image",),
    )
