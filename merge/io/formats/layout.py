"""Where scans from another AFM go in a mosaic: their own scan offsets, or a grid.

Shared by ``mosaic-afm import`` and the offline upload of the API; both turn a
:class:`LayoutError` into their own kind of refusal (exit 2, HTTP 422).
"""

from __future__ import annotations

from collections.abc import Sequence

from merge.core.errors import listed
from merge.io.formats.image import AfmImage

Place = tuple[tuple[float, float], int | None, int | None]  # origin (m), row, col


#: Degrees of scan rotation past which a file's offset does not place it.
MAX_ROTATION = 1.0


class LayoutError(ValueError):
    """The scans cannot be placed as asked; the message says what to give."""


def scan_places(
    images: Sequence[AfmImage],
    grid: tuple[int, int] | None = None,
    *,
    overlap: tuple[float, float] | None = None,
    order: str = "snake",
    names: Sequence[str] | None = None,
) -> list[Place]:
    """Origin (pixel (0, 0), metres) and grid cell of every scan, in the order given.

    Without ``grid`` the files' scan offsets place them: every file must have one, none may
    share one, and none may be scanned rotated in the scan plane (more than
    :data:`MAX_ROTATION` degrees: its offset alone does not place it); the messages name the
    files (``names``, else their numbers). With ``grid = (rows, cols)`` the scans fill it in
    acquisition ``order`` ("snake" or "raster") with the nominal pitch of the first scan's
    size and ``overlap`` (fractions).
    """
    label = list(names) if names is not None else [f"file {k + 1}" for k in range(len(images))]
    if grid is None:
        offsets = [im.offset for im in images]
        missing = [n for n, o in zip(label, offsets, strict=True) if o is None]
        if missing:
            raise LayoutError(
                f"{listed(missing)} carry no scan offset, so nothing says where they lie: "
                "give the grid and the overlap (--grid ROWSxCOLS --overlap OX,OY)"
            )
        rotated = [
            f"{n} ({float(im.metadata['rotation_deg']):g}°)"
            for n, im in zip(label, images, strict=True)
            if abs(float(im.metadata.get("rotation_deg", "0"))) > MAX_ROTATION
        ]
        if rotated:
            raise LayoutError(
                f"{listed(rotated)} were scanned rotated in the scan plane: their offsets do "
                "not place them; merge scans taken without scan rotation, or give the grid"
            )
        groups: dict[tuple[float, float] | None, list[str]] = {}
        for n, o in zip(label, offsets, strict=True):
            groups.setdefault(o, []).append(n)
        shared = "; ".join(listed(g) for g in groups.values() if len(g) > 1)
        if shared:
            raise LayoutError(
                f"{shared} share one scan offset, so the offsets do not lay out a mosaic: "
                "give the grid and the overlap"
            )
        return [(o, None, None) for o in offsets if o is not None]
    rows, cols = grid
    if rows * cols != len(images):
        raise LayoutError(f"a {rows} x {cols} grid needs {rows * cols} files, got {len(images)}")
    if overlap is None:
        raise LayoutError("a grid needs the overlap (fractions along x and y)")
    ny, nx = images[0].heights.shape
    w, h = nx * images[0].pixel_size[0], ny * images[0].pixel_size[1]
    if not all(0 <= o < 1 for o in overlap):
        raise LayoutError(f"overlaps must be fractions in [0, 1), got {overlap}")
    if rows < 1 or cols < 1:
        raise LayoutError(f"a grid needs a row and a column at least, got {rows} x {cols}")
    step = (w * (1 - overlap[0]), h * (1 - overlap[1]))
    out: list[Place] = []
    for r in range(rows):  # the files in acquisition order: snake (row 1 right to left), raster
        cs = range(cols - 1, -1, -1) if order == "snake" and r % 2 else range(cols)
        out.extend(((c * step[0], r * step[1]), r, c) for c in cs)
    return out
