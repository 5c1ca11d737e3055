"""Planning a mosaic: a region of interest cut into overlapping patches, in snake order.

Pure: an ROI (stage frame, metres), a patch (size and pixels) and overlaps in; the grid out,
centred on the ROI and covering it, validated against what the instrument can do. Every
problem is a :class:`PlanError` naming the field to fix (HTTP 422 at the API).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from hardware.envelope import ScanEnvelope
from hardware.mosaic_plan import PlannedPatch, snake_grid
from hardware.protocols import SEMImage


class PlanError(ValueError):
    """A plan the instrument cannot do; ``field`` names the input to fix."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


@dataclass(frozen=True)
class InstrumentLimits:
    """What a plan must respect (metres): the ranges, and what a scan may ask of the
    instrument on its sample (``scan``: speed against the force loop, time against drift)."""

    fine_range: tuple[float, float] = (1.6e-6, 1.6e-6)
    travel: tuple[tuple[float, float], tuple[float, float]] = ((-6e-3, 6e-3), (-6e-3, 6e-3))
    min_pixels: int = 8
    max_pixels: int = 4096
    max_patches: int = 2500
    max_overlap: float = 0.9
    scan: ScanEnvelope = field(default_factory=ScanEnvelope)
    #: the finest pixel the stage's sensors and the merge make sense of, metres
    min_pitch: float = 0.5e-9
    #: pixels an overlap must span for the merge to match two patches
    min_overlap_pixels: int = 3


@dataclass(frozen=True)
class Roi:
    """A rectangle in the stage frame: lower-left corner ``(x, y)`` and size, metres."""

    x: float
    y: float
    width: float
    height: float

    @classmethod
    def from_sem(cls, image: SEMImage, col: float, row: float, width: float, height: float) -> Roi:
        """The stage rectangle covering an SEM pixel rectangle (corner ``col, row``, size in
        pixels): on an image rotated against the stage, the rectangle drawn is a rotated one
        on the stage, and the ROI the stage-aligned rectangle around it."""
        corners = [image.to_stage(c, r) for c in (col, col + width) for r in (row, row + height)]
        xs, ys = [p[0] for p in corners], [p[1] for p in corners]
        return cls(min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys))


@dataclass(frozen=True)
class PatchSpec:
    """Scan range ``(width, height)`` (metres) and pixels ``(nx, ny)`` of every patch."""

    width: float
    height: float
    pixels: tuple[int, int]

    @property
    def pixel_size(self) -> tuple[float, float]:
        return self.width / self.pixels[0], self.height / self.pixels[1]


@dataclass(frozen=True)
class Plan:
    roi: Roi
    patch: PatchSpec
    overlap: tuple[float, float]
    rows: int
    cols: int
    patches: list[PlannedPatch]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` covered by the grid, metres."""
        xs = [p.origin[0] for p in self.patches]
        ys = [p.origin[1] for p in self.patches]
        return min(xs), min(ys), max(xs) + self.patch.width, max(ys) + self.patch.height


def _count(span: float, size: float, overlap: float) -> int:
    """Patches of ``size`` overlapping by ``overlap`` needed to cover ``span``."""
    if span <= size:
        return 1
    return math.ceil((span - size) / (size * (1.0 - overlap)) - 1e-9) + 1


def _finite_positive(value: float, field: str) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise PlanError(field, f"must be a positive number of metres, got {value!r}")


def check_scan(patch: PatchSpec, line_rate: float, limits: InstrumentLimits) -> None:
    """Refuse a scan the instrument cannot make safely: a line rate outside the scanner's
    range, a tip faster than the force loop follows on the sample's slopes, a patch longer
    than Z's range lasts against drift (:class:`PlanError` on ``line_rate``), or a pixel
    finer than :attr:`InstrumentLimits.min_pitch` (on ``patch.pixels``)."""
    if not (isinstance(line_rate, int | float) and math.isfinite(line_rate)):
        raise PlanError(
            "line_rate", f"must be a finite number of lines per second, got {line_rate!r}"
        )
    problems = limits.scan.problems(width=patch.width, lines=patch.pixels[1], line_rate=line_rate)
    if problems:
        raise PlanError("line_rate", "; ".join(problems))
    pitch = min(patch.pixel_size)
    if pitch < limits.min_pitch:
        raise PlanError(
            "patch.pixels",
            f"a pixel of {pitch * 1e9:.3g} nm is finer than the {limits.min_pitch * 1e9:g} nm "
            "the stage's sensors and the merge resolve: use fewer pixels",
        )


def plan_mosaic(
    roi: Roi,
    patch: PatchSpec,
    overlap: tuple[float, float],
    *,
    limits: InstrumentLimits | None = None,
    line_rate: float | None = None,
) -> Plan:
    """The snake-ordered grid of ``patch`` covering ``roi`` with ``overlap`` (fractions),
    scanned at ``line_rate`` (lines per second; checked by :func:`check_scan` when given)."""
    lim = limits or InstrumentLimits()
    for value, name in ((roi.width, "roi.width"), (roi.height, "roi.height")):
        _finite_positive(value, name)
    for value, name in ((roi.x, "roi.x"), (roi.y, "roi.y")):
        if not math.isfinite(value):
            raise PlanError(name, f"must be a finite number of metres, got {value!r}")
    for value, name, (lo, hi) in (
        (roi.width, "roi.width", lim.travel[0]),
        (roi.height, "roi.height", lim.travel[1]),
    ):
        if value > hi - lo:
            raise PlanError(
                name, f"{value:.3g} m is more than the stage's travel of {(hi - lo) * 1e3:g} mm"
            )
    for value, name, fine in (
        (patch.width, "patch.width", lim.fine_range[0]),
        (patch.height, "patch.height", lim.fine_range[1]),
    ):
        _finite_positive(value, name)
        if value > fine:
            raise PlanError(
                name, f"{value * 1e6:.3g} µm exceeds the fine scan range of {fine * 1e6:.3g} µm"
            )
    if len(patch.pixels) != 2:
        raise PlanError("patch.pixels", "must be two whole numbers [nx, ny]")
    for n, axis in zip(patch.pixels, "xy", strict=True):
        if (
            not isinstance(n, int)
            or isinstance(n, bool)
            or not lim.min_pixels <= n <= lim.max_pixels
        ):
            raise PlanError(
                "patch.pixels",
                f"{axis}: {n!r} pixels; use a whole number in {lim.min_pixels}..{lim.max_pixels}",
            )
    if len(overlap) != 2:
        raise PlanError("overlap", "must be two fractions [ox, oy]")
    for o, axis in zip(overlap, "xy", strict=True):
        if not (isinstance(o, int | float) and math.isfinite(o) and 0.0 <= o < lim.max_overlap):
            raise PlanError("overlap", f"{axis}: {o!r}; use a fraction in [0, {lim.max_overlap})")
    if line_rate is not None:
        check_scan(patch, line_rate, lim)
    cols = _count(roi.width, patch.width, overlap[0])
    rows = _count(roi.height, patch.height, overlap[1])
    for count, o, n, axis in ((cols, overlap[0], patch.pixels[0], "x"),
                              (rows, overlap[1], patch.pixels[1], "y")):  # fmt: skip
        if count > 1 and o * n < lim.min_overlap_pixels:
            raise PlanError(
                "overlap",
                f"{axis}: an overlap of {o:g} spans {o * n:.3g} of {n} pixels; the merge needs "
                f"{lim.min_overlap_pixels} at least to match neighbours: raise the overlap",
            )
    if rows * cols > lim.max_patches:
        raise PlanError(
            "roi",
            f"needs {rows} x {cols} = {rows * cols} patches, more than {lim.max_patches}: "
            "shrink the ROI, enlarge the patches or lower the overlap",
        )
    span_x = patch.width + (cols - 1) * patch.width * (1 - overlap[0])
    span_y = patch.height + (rows - 1) * patch.height * (1 - overlap[1])
    start = (
        roi.x + roi.width / 2 - span_x / 2,
        roi.y + roi.height / 2 - span_y / 2,
    )
    # the stage stands at minus the patch's place, plus where the raster starts in the fine
    # range: keep a fine range's margin so that no accepted patch asks past its travel
    (tx0, tx1), (ty0, ty1) = lim.travel
    fx, fy = lim.fine_range
    tx0, tx1, ty0, ty1 = tx0 + fx, tx1 - fx, ty0 + fy, ty1 - fy
    if start[0] < tx0 or start[0] + span_x > tx1 or start[1] < ty0 or start[1] + span_y > ty1:
        raise PlanError(
            "roi",
            f"the grid spans x {start[0] * 1e3:.3f}..{(start[0] + span_x) * 1e3:.3f} mm, "
            f"y {start[1] * 1e3:.3f}..{(start[1] + span_y) * 1e3:.3f} mm, outside the stage "
            f"travel x {tx0 * 1e3:g}..{tx1 * 1e3:g} mm, y {ty0 * 1e3:g}..{ty1 * 1e3:g} mm",
        )
    patches = snake_grid(
        rows, cols, patch_size=(patch.width, patch.height), overlap=overlap, start=start
    )
    return Plan(roi=roi, patch=patch, overlap=overlap, rows=rows, cols=cols, patches=patches)
