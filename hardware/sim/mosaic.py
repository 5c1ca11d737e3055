"""Scan a whole mosaic on the simulated instrument, in snake order, through the procedures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hardware.mosaic_plan import PlannedPatch, snake_grid
from hardware.procedures import PatchResult, acquire_patch
from hardware.sim.instrument import SimulatedAFM

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ScannedPatch:
    """One patch as scanned: heights (rows along y), nominal origin and pixel size (metres)."""

    plan: PlannedPatch
    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    line_times: FloatArray


def acquire_on(
    afm: SimulatedAFM,
    *,
    origin: tuple[float, float],
    size: tuple[float, float],
    pixels: tuple[int, int],
    line_rate: float,
) -> PatchResult:
    """One patch on the simulated instrument through the real procedure
    (:func:`~hardware.procedures.acquire_patch`): its stage, robot, loop and recorder."""
    return acquire_patch(
        stage_x=afm.stage_x,
        stage_y=afm.stage_y,
        x=afm.robot_x,
        y=afm.robot_y,
        z=afm.robot_z,
        loop=afm,
        probe=afm,
        recorder=afm,
        origin=origin,
        size=size,
        pixels=pixels,
        line_rate=line_rate,
    )


def scan_mosaic(
    afm: SimulatedAFM,
    *,
    rows: int,
    cols: int,
    patch_size: tuple[float, float],
    pixels: tuple[int, int],
    overlap: tuple[float, float],
    start: tuple[float, float] = (0.0, 0.0),
    line_rate: float = 2.0,
    on_patch: Callable[[ScannedPatch], None] | None = None,
) -> list[ScannedPatch]:
    """Move, land, scan and retract every patch of a snake-ordered grid.

    ``on_patch`` is called as soon as each patch is scanned (store it at once).
    """
    plan = snake_grid(rows, cols, patch_size=patch_size, overlap=overlap, start=start)
    out = []
    for planned in plan:
        result = acquire_on(
            afm, origin=planned.origin, size=patch_size, pixels=pixels, line_rate=line_rate
        )
        patch = ScannedPatch(
            plan=planned,
            heights=result.lines.heights,
            origin=result.origin,
            pixel_size=result.lines.pixel_size,
            line_times=result.lines.line_times,
        )
        out.append(patch)
        if on_patch is not None:
            on_patch(patch)
    return out
