"""Options of a merge."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Method = Literal["default", "paper", "nominal", "zlevel"]
METHODS: tuple[Method, ...] = ("default", "paper", "nominal", "zlevel")


@dataclass(frozen=True)
class MergeConfig:
    """How to merge a patch set.

    Attributes
    ----------
    method
        "default" (coarse start, then full-resolution point-to-plane GPA on all patches),
        "paper" (the published GPA-ICP on down-sampled points), "nominal" (no correction: the
        patches where the stage put them) or "zlevel" (Z offsets only).
    cell
        down-sampling cell side, metres; default the raster (line) spacing, i.e. the larger
        pixel pitch of the patches.
    max_iter
        iteration cap; default 40 for "default", 200 for "paper".
    max_shift
        largest XY error of a patch relative to its neighbour that the coarse start
        searches, metres; default half the smaller side of the smallest patch.
    coarse_cell
        cell the coarse start correlates the patches on, metres; default
        :func:`merge.start.coarse_cell` (a whole multiple of the finest pixel pitch, as fine
        as a budget of cells allows). Finer keeps finer texture, at a cost.
    init
        "auto" runs the robust coarse start (Z offsets and XY by correlation); "nominal"
        starts from the nominal placement.
    pixel_size
        mosaic pixel pitch (dx, dy), metres; default the finest patch pitch.
    feather
        blending ramp at patch borders, fraction of a patch's smaller side.
    self_calibrate
        measure the scanner's own bend of rows and columns, shared by every patch
        (an open-loop piezo's hysteresis and creep), from the overlaps of a first merge, take
        it out of every patch and merge again (:mod:`merge.refine.scanner`; "default" method only).
        For scans from a scanner that does not read its own position; it costs a second merge.
    """

    method: Method = "default"
    cell: float | None = None
    max_iter: int | None = None
    max_shift: float | None = None
    coarse_cell: float | None = None
    init: Literal["auto", "nominal"] = "auto"
    pixel_size: tuple[float, float] | None = None
    feather: float = 0.15
    self_calibrate: bool = False

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.cell is not None and not (math.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"cell must be a positive length in metres, got {self.cell}")
        if self.max_iter is not None and (not isinstance(self.max_iter, int) or self.max_iter < 1):
            raise ValueError(f"max_iter must be a positive integer, got {self.max_iter}")
        if self.max_shift is not None and not (
            math.isfinite(self.max_shift) and self.max_shift > 0
        ):
            raise ValueError(f"max_shift must be a positive length in metres, got {self.max_shift}")
        if self.coarse_cell is not None and not (
            math.isfinite(self.coarse_cell) and self.coarse_cell > 0
        ):
            raise ValueError(
                f"coarse_cell must be a positive length in metres, got {self.coarse_cell}"
            )
        if self.init not in ("auto", "nominal"):
            raise ValueError(f"init must be 'auto' or 'nominal', got {self.init!r}")
        if self.pixel_size is not None and (
            len(self.pixel_size) != 2
            or not all(math.isfinite(v) and v > 0 for v in self.pixel_size)
        ):
            raise ValueError(f"pixel_size must be two positive lengths, got {self.pixel_size}")
        if not 0 <= self.feather <= 0.5:
            raise ValueError(f"feather must be in [0, 0.5], got {self.feather}")
        if not isinstance(self.self_calibrate, bool):
            raise ValueError(f"self_calibrate must be true or false, got {self.self_calibrate!r}")
        if self.self_calibrate and self.method != "default":
            raise ValueError(
                f"self_calibrate needs the default method (it refines a full-resolution merge), "
                f"got method {self.method!r}"
            )

    def as_dict(self) -> dict[str, object]:
        """The options as JSON-ready values (for the result file)."""
        return {
            "method": self.method,
            "cell": self.cell,
            "max_iter": self.max_iter,
            "max_shift": self.max_shift,
            "coarse_cell": self.coarse_cell,
            "init": self.init,
            "pixel_size": list(self.pixel_size) if self.pixel_size else None,
            "feather": self.feather,
            "self_calibrate": self.self_calibrate,
        }
