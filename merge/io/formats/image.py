"""What every reader returns, and the errors they raise.

Orientation (the project's, for every format): ``heights[i, j]`` lies at
``(x0 + j * dx, y0 + i * dy)`` with y growing with ``i``: row 0 is the bottom of the image.
Gwyddion shows data top row first, so its data fields are this array flipped vertically;
every reader and writer converts, and the tests check each format against Gwyddion itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Channel names that mean topography, most preferred first (case-insensitive prefixes).
TOPOGRAPHY = ("z-axis", "height", "topography", "z", "zsensor", "z sensor")


class FormatError(ValueError):
    """The file cannot be read as asked; the message names the file and what is wrong."""


@dataclass(frozen=True)
class AfmImage:
    """One channel of an AFM file.

    heights : (ny, nx) in the channel's unit (metres for topography), rows along +y.
    pixel_size : (dx, dy) metres.
    offset : stage/scan position of pixel (0, 0), metres, when the file has one.
    channel : the channel read; channels : every channel the file holds.
    unit : of ``heights`` ("m" for topography).
    """

    heights: FloatArray
    pixel_size: tuple[float, float]
    channel: str
    unit: str = "m"
    offset: tuple[float, float] | None = None
    channels: tuple[str, ...] = ()
    metadata: dict[str, str] = field(default_factory=dict)


def choose_channel(path: str, channels: list[str], wanted: str | None) -> int:
    """Index of ``wanted`` (exact, then case-insensitive), else of the topography channel."""
    if not channels:
        raise FormatError(f"{path}: the file holds no image channel")
    if wanted is not None:
        for i, name in enumerate(channels):
            if name == wanted:
                return i
        for i, name in enumerate(channels):
            if name.lower() == wanted.lower():
                return i
        raise FormatError(f"{path}: no channel {wanted!r}; channels: {', '.join(channels)}")
    for prefix in TOPOGRAPHY:
        for i, name in enumerate(channels):
            if name.lower().startswith(prefix):
                return i
    raise FormatError(
        f"{path}: no height channel among {', '.join(channels)}; choose one with --channel"
    )


def top_down_bands(ny: int, nx: int, *, itemsize: int, budget: int) -> list[tuple[int, int]]:
    """Row ranges ``[lo, hi)`` of a map of ``ny`` rows of ``nx`` values (``itemsize`` bytes
    each), at most ``budget`` bytes a band (a row at least), the top row (``ny - 1``) first:
    the order of TIFF and Gwyddion files, whose first row is the top of the image. A large
    map is converted and written a band at a time."""
    rows = max(1, budget // (itemsize * max(nx, 1)))
    return [(max(0, hi - rows), hi) for hi in range(ny, 0, -rows)]
