"""The SEM-to-stage calibration: where an SEM image's pixels lie on the sample stage, measured
from images taken before and after known stage moves (as Micro-Manager's pixel calibrator and
SerialEM's stage calibration measure it). Pure: images and moves in, an affine map out.

A stage move ``m`` (metres) moves the sample under the SEM, so the image's content moves by
``A^-1 m`` pixels, ``A`` the 2 x 2 map from pixel steps (column, row) to stage metres. Each
move's image shift is measured by phase correlation with a sub-pixel peak; ``A`` is fitted to
every move by least squares, with its residual (pixels) and the uncertainty of its entries.
The map's offset (where pixel (0, 0) lies on the sample, at the stage position the reference
image was taken at) needs one point known in both frames (the tip in the image, or a feature
the AFM scanned), given to :func:`calibrate` as ``anchor``; an image taken at another stage
position lies shifted by the stage's move (:meth:`Calibration.to_stage`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]

#: Standard deviations of the correlation a peak must stand above the rest to be trusted
#: (two unrelated noise images reach about 5).
MIN_CLARITY = 12.0
#: The next highest correlation peak, over the highest, past which a shift is ambiguous
#: (the smallest moves, made before any prediction, are judged by it).
MAX_RIVAL = 0.8
#: Pixels around a predicted shift its peak is looked for in.
NEAR = 8.0
#: The fit's RMS residual past which a calibration is refused: this fraction of the moves'
#: RMS length (a stage that went elsewhere, a sample that slipped), never under
#: :data:`MIN_RESIDUAL` pixels (what the stage's sensor errors alone leave in a small field).
MAX_RESIDUAL = 0.02
MIN_RESIDUAL = 0.5
#: Pixels an image must shift by, at least, for a move to measure anything.
MIN_SHIFT = 2.0


class CalibrationError(ValueError):
    """A calibration that cannot be trusted; the message says why and what to change."""


@dataclass(frozen=True)
class Shift:
    """How far an image's content moved (columns, rows; pixels) and how clearly: the
    correlation peak's height over the rest of the correlation, in its standard deviations
    (its peak-to-sidelobe ratio)."""

    columns: float
    rows: float
    clarity: float
    #: the next highest peak over the highest (near 1: the field repeats itself)
    rival: float = 0.0


def _peak(a: float, b: float, c: float) -> float:
    """Where a parabola through three neighbouring values peaks, from the middle one."""
    denominator = a - 2 * b + c
    return 0.0 if denominator == 0 else 0.5 * (a - c) / denominator


def _correlate(a: FloatArray, b: FloatArray, near: tuple[float, float] | None = None) -> Shift:
    """The translation by phase correlation: whitened cross-power spectrum, a Hann window
    against the edges, the peak to a fraction of a pixel (a first estimate: the window and
    the content's own aliasing bias it by a tenth of a pixel)."""
    window = np.outer(np.hanning(a.shape[0]), np.hanning(a.shape[1]))
    fa = np.fft.fft2((a - a.mean()) * window)
    fb = np.fft.fft2((b - b.mean()) * window)
    cross = fb * np.conj(fa)
    cross /= np.maximum(np.abs(cross), 1e-300)
    surface = np.fft.ifft2(cross).real
    search = surface
    if near is not None:  # the peak within :data:`NEAR` px of where it is expected
        ny, nx = surface.shape
        dr = (np.arange(ny)[:, None] - near[1] + ny / 2) % ny - ny / 2
        dc = (np.arange(nx)[None, :] - near[0] + nx / 2) % nx - nx / 2
        search = np.where(np.hypot(dr, dc) <= NEAR, surface, -np.inf)
    r, c = (int(v) for v in np.unravel_index(int(np.argmax(search)), surface.shape))
    ny, nx = surface.shape
    dr = r + _peak(*(float(surface[(r + d) % ny, c]) for d in (-1, 0, 1)))
    dc = c + _peak(*(float(surface[r, (c + d) % nx]) for d in (-1, 0, 1)))
    rest = np.ones(surface.shape, dtype=bool)
    rest[np.ix_(np.arange(r - 5, r + 6) % ny, np.arange(c - 5, c + 6) % nx)] = False
    side = surface[rest]
    clarity = float((surface[r, c] - side.mean()) / max(float(side.std()), 1e-300))
    rival = float(side.max() / surface[r, c]) if surface[r, c] > 0 else 1.0
    dr = dr - ny if dr > ny / 2 else dr
    dc = dc - nx if dc > nx / 2 else dc
    return Shift(float(dc), float(dr), clarity, rival)


def _refine(a: FloatArray, b: FloatArray, start: Shift, *, steps: int = 12) -> Shift:
    """The translation refined where the two images overlap: ``a(x) = g b(x + d) + o`` by
    Gauss-Newton, ``b`` between its pixels by cubic splines (unbiased to about a
    fiftieth of a pixel where phase correlation was off by a tenth)."""
    ny, nx = a.shape
    coeffs = ndimage.spline_filter(b, order=3)
    rows, cols = np.mgrid[0:ny, 0:nx].astype(np.float64)
    d = np.array([start.columns, start.rows])
    gain, level = 1.0, 0.0

    def sample(r: FloatArray, c: FloatArray) -> FloatArray:
        out: FloatArray = ndimage.map_coordinates(coeffs, [r, c], order=3, prefilter=False)
        return out

    for _ in range(steps):
        r, c = rows + d[1], cols + d[0]
        inside = (r >= 3) & (r <= ny - 4) & (c >= 3) & (c <= nx - 4)
        if inside.sum() < 0.1 * a.size:
            break  # too little overlap to refine: the first estimate stands
        r, c, target = r[inside], c[inside], a[inside]
        value = sample(r, c)
        grad_c = sample(r, c + 0.5) - sample(r, c - 0.5)
        grad_r = sample(r + 0.5, c) - sample(r - 0.5, c)
        jacobian = np.column_stack([gain * grad_c, gain * grad_r, value, np.ones_like(value)])
        step, *_ = np.linalg.lstsq(jacobian, target - (gain * value + level), rcond=None)
        d += step[:2]
        gain, level = gain + step[2], level + step[3]
        if abs(step[0]) + abs(step[1]) < 1e-4:
            break
    return Shift(float(d[0]), float(d[1]), start.clarity, start.rival)


def phase_shift(
    before: FloatArray, after: FloatArray, *, near: tuple[float, float] | None = None
) -> Shift:
    """The translation of ``after``'s content against ``before``'s (both (ny, nx), one
    shape): phase correlation for where (:func:`_correlate`), then least squares on the
    overlap for how far exactly (:func:`_refine`). ``near`` (columns, rows): look for the
    peak within :data:`NEAR` pixels of there only (a sample that repeats itself has peaks
    alike one period apart)."""
    a, b = np.asarray(before, dtype=np.float64), np.asarray(after, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or min(a.shape) < 16:
        raise ValueError(f"need two 2-D images of one shape, 16 px at least: {a.shape}, {b.shape}")
    if near is None:
        return _refine(a, b, _correlate(a, b))
    # a shift expected: correlate where the two overlap there (a window over the whole of
    # both would weigh half of each against what the other does not hold)
    ic, ir = round(near[0]), round(near[1])
    ny, nx = a.shape
    if ny - abs(ir) < 16 or nx - abs(ic) < 16:
        raise CalibrationError(
            f"a shift of ({near[0]:.0f}, {near[1]:.0f}) px leaves the {nx} x {ny} px frames "
            "less than 16 px in common: use smaller moves"
        )
    rows_a, rows_b = slice(max(0, -ir), ny - max(0, ir)), slice(max(0, ir), ny - max(0, -ir))
    cols_a, cols_b = slice(max(0, -ic), nx - max(0, ic)), slice(max(0, ic), nx - max(0, -ic))
    rest = _correlate(a[rows_a, cols_a], b[rows_b, cols_b], (near[0] - ic, near[1] - ir))
    start = replace(rest, columns=rest.columns + ic, rows=rest.rows + ir)
    return _refine(a, b, start)


@dataclass(frozen=True)
class Calibration:
    """Where SEM pixels lie on the sample: ``matrix @ (column, row) + offset`` for an image
    taken with the sample stage at ``stage``, shifted by the stage's move for one taken
    elsewhere.

    matrix : (2, 2) metres per pixel step along the image's columns and rows.
    offset : sample position (metres) of pixel (0, 0)'s centre at ``stage``, as the SEM saw it
        at the end of the calibration (the drift the returns to the start measured taken in).
    stage : the sample stage's position the offset holds for, metres.
    residual_px : RMS misfit of the moves it was fitted to, pixels.
    sigma : standard deviations of the matrix's four entries, metres per pixel.
    field : the field of view it was measured at, metres (None: not said).
    """

    matrix: FloatArray
    offset: tuple[float, float]
    residual_px: float
    sigma: FloatArray
    stage: tuple[float, float] = (0.0, 0.0)
    field: float | None = None
    #: the image shift each move made, as measured
    shifts: tuple[Shift, ...] = ()

    @property
    def rotation_deg(self) -> float:
        """How far the image's column axis is turned from the stage's +x, degrees."""
        return math.degrees(math.atan2(self.matrix[1, 0], self.matrix[0, 0]))

    @property
    def scale(self) -> tuple[float, float]:
        """Metres per pixel along the columns and along the rows."""
        return (
            float(np.hypot(*self.matrix[:, 0])),
            float(np.hypot(*self.matrix[:, 1])),
        )

    @property
    def shear(self) -> float:
        """How far the two pixel axes are from perpendicular, as the cosine of their angle."""
        a, b = self.matrix[:, 0], self.matrix[:, 1]
        return float(a @ b / (np.hypot(*a) * np.hypot(*b)))

    @property
    def mirrored(self) -> bool:
        """Whether the image is mirrored against the stage (rows down, y up: the usual)."""
        return bool(np.linalg.det(self.matrix) < 0)

    def _offset(self, at: tuple[float, float] | None) -> FloatArray:
        move = np.zeros(2) if at is None else np.asarray(at) - np.asarray(self.stage)
        out: FloatArray = np.asarray(self.offset) - move
        return out

    def to_stage(
        self, column: float, row: float, *, at: tuple[float, float] | None = None
    ) -> tuple[float, float]:
        """The sample position of pixel ``(column, row)`` of an image taken with the stage
        ``at`` (default: where the calibration's reference was taken)."""
        x, y = self.matrix @ np.array([column, row]) + self._offset(at)
        return float(x), float(y)

    def to_pixel(
        self, x: float, y: float, *, at: tuple[float, float] | None = None
    ) -> tuple[float, float]:
        """The pixel of sample position ``(x, y)`` in an image taken with the stage ``at``."""
        c, r = np.linalg.solve(self.matrix, np.array([x, y]) - self._offset(at))
        return float(c), float(r)


def fit_matrix(
    moves: Sequence[tuple[float, float]],
    shifts: Sequence[Shift],
    *,
    intercept: bool = True,
) -> tuple[FloatArray, float, FloatArray]:
    """The 2 x 2 map from pixel steps to stage metres that best explains each stage ``move``
    (metres) by the image ``shift`` it made (``move = matrix @ shift + c``), its RMS residual
    in pixels, and the standard deviations of its entries (metres per pixel).

    With ``intercept`` the constant ``c`` is fitted too: every move starts where the stage's
    sensor read the start, so the sensor's error there (an encoder's periodic error, tens of
    nanometres) is common to all of them and would otherwise tilt the map; it needs four
    moves at least."""
    m = np.asarray(moves, dtype=np.float64)
    d = np.array([[s.columns, s.rows] for s in shifts], dtype=np.float64)
    directions = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
    singular = np.linalg.svd(directions, compute_uv=False) if len(m) else np.zeros(1)
    if len(m) < 2 or singular[-1] < 0.3 * singular[0] or np.linalg.matrix_rank(d) < 2:
        raise CalibrationError(
            "the moves must go along two directions at least (x and y), each seen in the image"
        )
    if intercept and len(m) < 4:
        raise CalibrationError(f"{len(m)} moves: four at least (along x and y, both ways)")
    design = np.column_stack([d, np.ones(len(d))]) if intercept else d
    solution, *_ = np.linalg.lstsq(design, m, rcond=None)  # design @ [matrix.T; c] = m
    matrix: FloatArray = np.asarray(solution[:2].T, dtype=np.float64)
    constant = solution[2] if intercept else np.zeros(2)
    predicted = np.linalg.solve(matrix, (m - constant).T).T  # the shifts the fit expects, px
    residual = float(np.sqrt(np.mean(np.sum((predicted - d) ** 2, axis=1))))
    unknowns = design.shape[1]
    variance = float(np.sum((design @ solution - m) ** 2)) / max(2 * (len(m) - unknowns), 1)
    spread = np.sqrt(np.diag(np.linalg.pinv(design.T @ design))[:2] * variance)
    sigma: FloatArray = np.vstack([spread, spread])  # each row of the matrix alike
    return matrix, residual, sigma


def calibrate(
    reference: FloatArray,
    moved: Sequence[tuple[tuple[float, float], FloatArray]],
    *,
    anchor: tuple[tuple[float, float], tuple[float, float]],
    stage: tuple[float, float] = (0.0, 0.0),
    field: float | None = None,
    returned: Sequence[FloatArray] | None = None,
) -> Calibration:
    """The calibration from a ``reference`` image and images ``moved`` after known stage
    moves (each ``(move, image)``, the move in metres from the reference's stage position).
    ``anchor`` is one point known in both frames: ``((column, row), (x, y))``, in the
    reference image, taken with the sample stage at ``stage``. ``returned``: an image taken
    back at the reference's stage position after each move (in the order the moves were
    made); what they show moved is drift (charging), taken out of each move's shift as the
    mean of the returns either side of it.

    Raises :class:`CalibrationError` when an image has too little structure to tell its
    shift (a peak less clear than :data:`MIN_CLARITY`), when it repeats itself (a rival peak
    past :data:`MAX_RIVAL` of it), when a move shifted the image less
    than :data:`MIN_SHIFT` pixels (the stage did not move, or moved too little), or when the
    fit leaves more than :data:`MAX_RESIDUAL` pixels of residual."""
    # the smallest moves first; once two directions are measured, the later (larger) moves
    # are looked for where the map so far puts them: a field that repeats itself has peaks
    # alike one period apart, and only the near one is the move
    order = sorted(range(len(moved)), key=lambda k: math.hypot(*moved[k][0]))
    found: dict[int, Shift] = {}
    for k in order:
        move, image = moved[k]
        near = None
        if len(found) >= 2:
            try:
                trial, _, _ = fit_matrix(
                    [moved[j][0] for j in found], list(found.values()), intercept=False
                )
                predicted = np.linalg.solve(trial, np.asarray(move))
                near = (float(predicted[0]), float(predicted[1]))
            except (CalibrationError, np.linalg.LinAlgError):
                near = None
        shift = phase_shift(reference, image, near=near)
        if near is not None and shift.clarity < MIN_CLARITY:
            elsewhere = phase_shift(reference, image)
            if elsewhere.clarity >= MIN_CLARITY:
                raise CalibrationError(
                    f"the moves disagree: move {k + 1} ({move[0] * 1e6:.3g}, "
                    f"{move[1] * 1e6:.3g} µm) shifted the image by ({elsewhere.columns:.1f}, "
                    f"{elsewhere.rows:.1f}) px where the moves before put it at ({near[0]:.1f}, "
                    f"{near[1]:.1f}): the stage did not go where it was told"
                )
        if shift.clarity < MIN_CLARITY:
            raise CalibrationError(
                f"move {k + 1}: the images do not correlate clearly (a peak {shift.clarity:.1f} "
                "standard deviations high): too little structure in the field; pick a "
                "textured area"
            )
        if near is None and shift.rival > MAX_RIVAL:
            raise CalibrationError(
                f"move {k + 1}: two places fit alike (the second peak {shift.rival:.0%} of the "
                "first): the field repeats itself (a periodic sample); use a smaller field or "
                "another area"
            )
        if math.hypot(shift.columns, shift.rows) < MIN_SHIFT:
            raise CalibrationError(
                f"move {k + 1} ({move[0] * 1e6:.3g}, {move[1] * 1e6:.3g} µm) shifted the image "
                f"by {math.hypot(shift.columns, shift.rows):.2f} px: the stage did not move, or "
                "moved too little for this field"
            )
        found[k] = shift
    drift, since = _drift(reference, returned, len(moved))
    shifts = [
        replace(found[k], columns=found[k].columns - drift[k][0], rows=found[k].rows - drift[k][1])
        for k in range(len(moved))
    ]
    matrix, residual, sigma = fit_matrix([m for m, _ in moved], shifts)
    lengths = [math.hypot(s.columns, s.rows) for s in shifts]
    allowed = max(
        MIN_RESIDUAL, MAX_RESIDUAL * math.sqrt(sum(v * v for v in lengths) / len(lengths))
    )
    if residual > allowed:
        raise CalibrationError(
            f"the moves disagree by {residual:.2f} px RMS (more than {allowed:.2f}): the stage "
            "did not go where it was told, or the sample charged between images"
        )
    (column, row), (x, y) = anchor
    # the anchor holds in the reference; the image has drifted by ``since`` pixels by the
    # last return: the offset as it is now, at the end of the calibration
    offset = np.array([x, y]) - matrix @ (np.array([column, row]) + np.asarray(since))
    return Calibration(
        matrix,
        (float(offset[0]), float(offset[1])),
        residual,
        sigma,
        stage,
        field,
        tuple(shifts),
    )


#: Pixels the image may have moved between two returns to the start, at most: past it the
#: sample drifts too fast (charging) or the stage does not come back, and no map is trusted.
MAX_DRIFT = 3.0


def _drift(
    reference: FloatArray, returned: Sequence[FloatArray] | None, count: int
) -> tuple[list[tuple[float, float]], tuple[float, float]]:
    """The drift (columns, rows) at each of ``count`` moves (the mean of the returns to the
    start either side of it) and at the last return; none given: none."""
    if returned is None:
        return [(0.0, 0.0)] * count, (0.0, 0.0)
    if len(returned) != count:
        raise ValueError(f"{len(returned)} images taken back at the start for {count} moves")
    out = []
    before = (0.0, 0.0)
    for k, image in enumerate(returned):
        back = phase_shift(reference, image, near=before)
        if back.clarity < MIN_CLARITY:
            raise CalibrationError(
                f"back at the start after move {k + 1}, the image does not correlate with the "
                "first: the sample changed under the beam (contamination, charging)"
            )
        now = (back.columns, back.rows)
        if math.hypot(now[0] - before[0], now[1] - before[1]) > MAX_DRIFT:
            raise CalibrationError(
                f"back at the start after move {k + 1}, the image had moved by "
                f"({now[0] - before[0]:.1f}, {now[1] - before[1]:.1f}) px since the return "
                "before: the sample drifts (charging) or the stage does not come back; let it "
                "settle, lower the dose or use a conductive area"
            )
        out.append(((before[0] + now[0]) / 2, (before[1] + now[1]) / 2))
        before = now
    return out, before
