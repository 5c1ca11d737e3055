"""The patch model: overlapping height maps at nominal stage positions.

A :class:`Patch` is one AFM topography: a 2-D array of heights (metres, rows along y, NaN for
missing points) whose pixel ``(i, j)`` lies at the nominal stage position
``(x0 + j * dx, y0 + i * dy)``. Nominal means "where the coarse stage was told to go"; the merge
finds where each patch really is.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from merge.core.errors import PatchSetError
from merge.core.noise import estimate_noise

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Patch:
    """One height map at its nominal place.

    Parameters
    ----------
    id : str
        Unique name of the patch within its set.
    heights : (ny, nx) float array
        Heights in metres, rows along y (first row = first scan line), NaN where missing.
    origin : (x0, y0)
        Nominal stage position of pixel (0, 0), metres.
    pixel_size : (dx, dy)
        Pixel pitch along x (fast axis, columns) and y (rows), metres, both positive.
    order : int
        Acquisition order (0 first).
    row, col : int or None
        Grid position when the patch came from a planned grid.
    """

    id: str
    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    order: int = 0
    row: int | None = None
    col: int | None = None
    source: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        name = f"patch {self.id!r}"
        if not isinstance(self.id, str) or not self.id:
            raise PatchSetError("every patch needs a non-empty string id")
        heights = np.asarray(self.heights)
        if heights.ndim != 2:
            raise PatchSetError(
                f"{name}: heights must be a 2-D array (rows along y), got shape {heights.shape}"
            )
        if heights.shape[0] < 2 or heights.shape[1] < 2:
            raise PatchSetError(f"{name}: needs at least 2 x 2 pixels, got {heights.shape}")
        if not np.issubdtype(heights.dtype, np.number) or np.iscomplexobj(heights):
            raise PatchSetError(f"{name}: heights must be real numbers, got dtype {heights.dtype}")
        heights = heights.astype(np.float64, copy=False)
        if np.isinf(heights).any():
            raise PatchSetError(f"{name}: heights contain infinite values; use NaN for missing")
        if not np.isfinite(heights).any():
            raise PatchSetError(f"{name}: heights are all NaN (no measured point)")
        object.__setattr__(self, "heights", heights)
        origin = _pair(self.origin, f"{name}: origin")
        pixel = _pair(self.pixel_size, f"{name}: pixel_size")
        if pixel[0] <= 0 or pixel[1] <= 0:
            raise PatchSetError(f"{name}: pixel_size must be positive, got {list(pixel)}")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "pixel_size", pixel)

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``."""
        ny, nx = self.heights.shape
        return int(ny), int(nx)

    @property
    def extent(self) -> tuple[float, float]:
        """Nominal size ``(width, height)`` from first to last pixel centre, metres."""
        ny, nx = self.shape
        return (nx - 1) * self.pixel_size[0], (ny - 1) * self.pixel_size[1]

    @property
    def footprint(self) -> tuple[float, float, float, float]:
        """Nominal ``(xmin, ymin, xmax, ymax)`` of the pixel centres, metres."""
        w, h = self.extent
        return self.origin[0], self.origin[1], self.origin[0] + w, self.origin[1] + h

    @property
    def center(self) -> tuple[float, float]:
        """Nominal centre of the patch, metres."""
        x0, y0, x1, y1 = self.footprint
        return 0.5 * (x0 + x1), 0.5 * (y0 + y1)

    @cached_property
    def median_height(self) -> float:
        """Median of the measured heights, metres (once per patch: the start, the refinement
        and the render each place the patch's frame at it)."""
        return float(np.nanmedian(self.heights))

    @cached_property
    def noise(self) -> float:
        """Standard deviation of the white height noise, metres
        (:func:`merge.core.noise.estimate_noise`, once per patch)."""
        return estimate_noise(self.heights)

    def pixel_coordinates(self) -> tuple[FloatArray, FloatArray]:
        """Nominal stage coordinates of every pixel: ``(X, Y)``, each ``(ny, nx)``, metres."""
        ny, nx = self.shape
        x = self.origin[0] + np.arange(nx) * self.pixel_size[0]
        y = self.origin[1] + np.arange(ny) * self.pixel_size[1]
        xx, yy = np.meshgrid(x, y)
        return xx, yy


def _pair(value: object, what: str) -> tuple[float, float]:
    try:
        seq = [float(v) for v in value]  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise PatchSetError(f"{what} must be two numbers, got {value!r}") from None
    if len(seq) != 2 or not all(np.isfinite(seq)):
        raise PatchSetError(f"{what} must be two finite numbers, got {value!r}")
    return seq[0], seq[1]


@dataclass(frozen=True, eq=False)
class PatchSet:
    """At least two patches with unique ids, kept in acquisition order."""

    patches: tuple[Patch, ...]

    def __init__(self, patches: Iterable[Patch]) -> None:
        items = tuple(patches)
        if len(items) < 2:
            raise PatchSetError(
                f"a patch set needs at least two patches to merge, got {len(items)}"
            )
        seen: set[str] = set()
        for p in items:
            if p.id in seen:
                raise PatchSetError(f"patch id {p.id!r} appears more than once; ids must be unique")
            seen.add(p.id)
        ordered = tuple(sorted(items, key=lambda p: (p.order, p.id)))
        object.__setattr__(self, "patches", ordered)

    def __len__(self) -> int:
        return len(self.patches)

    def __iter__(self) -> Iterator[Patch]:
        return iter(self.patches)

    def __getitem__(self, index: int) -> Patch:
        return self.patches[index]

    @property
    def ids(self) -> list[str]:
        """The patches' ids, in order."""
        return [p.id for p in self.patches]

    def subset(self, ids: Sequence[str]) -> PatchSet:
        """The patches named in ``ids`` (a merge of part of a run)."""
        wanted = set(ids)
        missing = wanted - set(self.ids)
        if missing:
            raise PatchSetError(f"no patch with id {sorted(missing)} in this set")
        return PatchSet(p for p in self.patches if p.id in wanted)
