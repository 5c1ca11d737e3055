"""Where the patches of a mosaic go: a grid of overlapping patches visited in snake order."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PlannedPatch:
    """One patch of a planned grid.

    ``index`` is the acquisition order; ``origin`` the nominal stage position of its pixel (0, 0)
    (metres), the lower-left corner of the patch.
    """

    index: int
    row: int
    col: int
    origin: tuple[float, float]


def snake_grid(
    rows: int,
    cols: int,
    *,
    patch_size: tuple[float, float],
    overlap: tuple[float, float],
    start: tuple[float, float] = (0.0, 0.0),
) -> list[PlannedPatch]:
    """Patches of ``patch_size`` (metres) overlapping by ``overlap`` (fractions), snake order.

    Row 0 is visited left to right, row 1 right to left and so on (paper, Fig. 2), so every patch
    but the first and the last has a neighbour scanned just before or after it. Rows go along +y.
    """
    if rows < 1 or cols < 1:
        raise ValueError(f"need at least one row and one column, got {rows} x {cols}")
    w, h = patch_size
    ox, oy = overlap
    if w <= 0 or h <= 0:
        raise ValueError(f"patch_size must be positive, got {patch_size}")
    if not (0 <= ox < 1 and 0 <= oy < 1):
        raise ValueError(f"overlaps must be in [0, 1), got {overlap}")
    step_x, step_y = w * (1 - ox), h * (1 - oy)
    out: list[PlannedPatch] = []
    for r in range(rows):
        cs = range(cols) if r % 2 == 0 else range(cols - 1, -1, -1)
        for c in cs:
            origin = (start[0] + c * step_x, start[1] + r * step_y)
            out.append(PlannedPatch(index=len(out), row=r, col=c, origin=origin))
    return out
