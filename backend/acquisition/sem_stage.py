"""The SEM-to-stage calibration on the instrument, and where an SEM frame lies on the stage.

The procedure (:func:`measure`): with the tip withdrawn and no run on the instrument, an SEM
frame at the stage's position, then one after each of :data:`MOVES` (the sample stage moved by
one to six steps along x and y, both ways) and one back at the start after each (what moved
there is drift, charging, taken out of the moves); the moves as the stage's sensors measured
them and the image shifts give the map (:func:`backend.sem_calibration.calibrate`). Its offset
needs one point known in both frames: the operator's ``anchor`` (the tip seen in the reference
image, at the sample point under the tip), else the SEM's field centred over the tip's raster
(its nominal mounting).

A frame taken later is placed through the calibration in force (:func:`place_frame`): the same
scan geometry scaled to its pixel, turned by any change of the scan rotation since, its field's
centre over the same lab point, the sample moved by the stage since.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from backend.sem_calibration import MIN_SHIFT, Calibration, CalibrationError, calibrate, phase_shift
from hardware.microscope import Microscope
from hardware.protocols import SEMFrame, SEMImage
from hardware.raster import wait_stopped

#: Stage moves of the calibration, in steps along (x, y): one to six steps along each axis,
#: both ways. Many lengths, so that the stage's sensor errors (an encoder's periodic error)
#: at the moves' ends average out rather than tilt the map.
MOVES = tuple(
    (k * sx, k * sy) for k in (1, 2, 3, 4, 5, 6) for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1))
)
#: The default step, as a fraction of the field of view (the longest move: half of it).
STEP = 1 / 12


def stage_position(m: Microscope) -> tuple[float, float]:
    """The sample stage's position as its sensors read it (metres)."""
    x, y = m.stage_x.position(), m.stage_y.position()
    if x is None or y is None:
        raise ValueError("the sample stage has no position sensors: it cannot calibrate the SEM")
    return x, y


def move_stage_to(m: Microscope, target: tuple[float, float]) -> tuple[float, float]:
    """Move the sample stage to ``target`` (metres), wait until it stops; where it reads."""
    m.stage_x.move_to(target[0])
    m.stage_y.move_to(target[1])
    wait_stopped(m.stage_x)
    wait_stopped(m.stage_y)
    return stage_position(m)


def measure(
    m: Microscope,
    *,
    field: float,
    pixels: int,
    step: float,
    dwell: float = 1e-6,
    detector: str = "SE",
    anchor: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> tuple[Calibration, float, list[list[float]]]:
    """The calibration (:class:`Calibration`), the scan rotation the SEM reported, and each
    move made with its shift (``[dx, dy, columns, rows]``); the stage ends where it began.
    The caller holds the instrument with the tip withdrawn."""
    sem = m.sem
    if sem is None:
        raise ValueError("this instrument has no SEM driver to calibrate")
    start = stage_position(m)
    reference = sem.acquire(field=field, pixels=pixels, dwell=dwell, detector=detector)
    moved: list[tuple[tuple[float, float], np.ndarray]] = []
    returned: list[np.ndarray] = []
    try:
        for kx, ky in MOVES:
            at = move_stage_to(m, (start[0] + kx * step, start[1] + ky * step))
            frame = sem.acquire(field=field, pixels=pixels, dwell=dwell, detector=detector)
            moved.append(((at[0] - start[0], at[1] - start[1]), frame.pixels))
            if len(moved) == 1:  # the first move tells whether the stage moves the image
                _moves_the_image(reference.pixels, frame.pixels, at, start)
            move_stage_to(m, start)  # and back: what moved meanwhile is drift
            back = sem.acquire(field=field, pixels=pixels, dwell=dwell, detector=detector)
            returned.append(back.pixels)
    finally:
        move_stage_to(m, start)
    if anchor is None:  # the field's centre over the lab origin: the sample point -start
        middle = (pixels - 1) / 2
        anchor = ((middle, middle), (-start[0], -start[1]))
    found = calibrate(
        reference.pixels, moved, anchor=anchor, stage=start, field=field, returned=returned
    )
    record = [[move[0], move[1], shift.columns, shift.rows]
              for (move, _), shift in zip(moved, found.shifts, strict=True)]  # fmt: skip
    return found, reference.rotation, record


def _moves_the_image(
    reference: np.ndarray, frame: np.ndarray, at: tuple[float, float], start: tuple[float, float]
) -> None:
    """Refuse at once, not after every frame, a first move that shifted the image by less
    than :data:`backend.sem_calibration.MIN_SHIFT` pixels."""
    shift = phase_shift(reference, frame)
    moved = math.hypot(shift.columns, shift.rows)
    if moved < MIN_SHIFT:
        raise CalibrationError(
            f"move 1 ({(at[0] - start[0]) * 1e6:.3g}, {(at[1] - start[1]) * 1e6:.3g} µm) "
            f"shifted the image by {moved:.2f} px: the stage did not move, or moved too little "
            "for this field"
        )


def _turn(matrix: np.ndarray, degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    out: np.ndarray = rot @ matrix
    return out


def place_frame(
    frame: SEMFrame,
    *,
    calibration: Calibration,
    pixels_then: int,
    rotation_then: float,
    stage_now: tuple[float, float],
) -> SEMImage:
    """Where ``frame`` lies on the stage through ``calibration`` (measured on frames of
    ``pixels_then`` at ``rotation_then`` degrees), the stage now at ``stage_now``."""
    if calibration.field is None:
        raise ValueError("a calibration without its field of view cannot be scaled")
    then = calibration.field / pixels_then
    matrix = _turn(calibration.matrix, frame.rotation - rotation_then) * (frame.pixel_size / then)
    middle_then = (pixels_then - 1) / 2
    centre_lab = np.asarray(calibration.to_stage(middle_then, middle_then)) + np.asarray(
        calibration.stage
    )  # the lab point the field's centre looks at
    n = frame.pixels.shape[0]
    middle = (n - 1) / 2
    origin = centre_lab - np.asarray(stage_now) - matrix @ np.array([middle, middle])
    size = (frame.pixel_size, frame.pixel_size)
    rows: Sequence[Sequence[float]] = matrix.tolist()
    return SEMImage(
        frame.pixels,
        (float(origin[0]), float(origin[1])),
        size,
        ((rows[0][0], rows[0][1]), (rows[1][0], rows[1][1])),
    )


def adjusted(
    calibration: Calibration,
    *,
    pixels_then: int,
    image_origin: tuple[float, float],
    image_matrix: np.ndarray,
    image_pixels: int,
    t_matrix: np.ndarray,
    t_offset: tuple[float, float],
) -> Calibration:
    """The calibration corrected by a registration: an image it placed (``image_origin``,
    ``image_matrix``, ``image_pixels`` a side) showed the sample point ``p`` where it said
    ``T(p) = t_matrix @ p + t_offset`` (a similarity, :mod:`merge.correlative`). The map's
    matrix is turned and scaled by ``T``'s inverse, the lab point its field's centre looks at
    moved so that the image would have been placed right."""
    if calibration.field is None:
        raise ValueError("a calibration without its field of view cannot be adjusted")
    inverse = np.linalg.inv(np.asarray(t_matrix, dtype=np.float64))
    middle_then = (pixels_then - 1) / 2
    centre_lab = np.asarray(calibration.to_stage(middle_then, middle_then)) + np.asarray(
        calibration.stage
    )
    middle = (image_pixels - 1) / 2
    image_m = np.asarray(image_matrix, dtype=np.float64)
    stage_then = centre_lab - np.asarray(image_origin) - image_m @ np.array([middle, middle])
    new_centre = inverse @ (centre_lab - stage_then - np.asarray(t_offset)) + stage_then
    matrix = inverse @ calibration.matrix
    offset = new_centre - np.asarray(calibration.stage) - matrix @ np.array([middle_then] * 2)
    return Calibration(
        matrix,
        (float(offset[0]), float(offset[1])),
        calibration.residual_px,
        calibration.sigma,
        calibration.stage,
        calibration.field,
    )
