"""The SEM-to-stage calibration recovers a rotated, scaled SEM from images before and after
known stage moves, and refuses what cannot be trusted."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from backend.sem_calibration import CalibrationError, calibrate, phase_shift
from hardware.sim.sem import SEMGeometry, SimulatedSEM, render_frame
from hardware.sim.surfaces import Chessboard, FoldedSurface

FIELD, PIXELS = 20e-6, 256
PITCH = FIELD / PIXELS


def _frame(
    sem: SimulatedSEM, geometry: SEMGeometry, stage: tuple[float, float], pixels: int = PIXELS
) -> np.ndarray:
    """The SEM's image with the sample stage at ``stage``: it shows sample point
    ``lab - stage`` at the lab point a pixel looks at."""
    ox, oy = geometry.offset
    moved = replace(geometry, offset=(ox - stage[0], oy - stage[1]))
    return render_frame(sem, moved, field=FIELD, pixels=pixels)


def _truth(geometry: SEMGeometry) -> np.ndarray:
    a = np.deg2rad(geometry.rotation)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return geometry.scale * rot @ np.diag([PITCH, -PITCH])  # rows go down the image


def test_phase_correlation_finds_a_sub_pixel_shift() -> None:
    sem = SimulatedSEM(FoldedSurface(seed=2), noise=0.02, seed=1)
    geometry = SEMGeometry(rotation=0.0, scale=1.0)
    before = _frame(sem, geometry, (0.0, 0.0))
    after = _frame(sem, geometry, (3.3 * PITCH, -1.6 * PITCH))  # the sample moves +x, -y
    shift = phase_shift(before, after)
    # content moves with the sample: +3.3 columns, and down the image 1.6 rows (y is up)
    assert shift.columns == pytest.approx(3.3, abs=0.1)
    assert shift.rows == pytest.approx(1.6, abs=0.1)
    assert shift.clarity > 3


@pytest.mark.parametrize(("rotation", "scale"), [(3.0, 1.025), (-7.5, 0.97), (0.0, 1.0)])
def test_a_rotated_scaled_sem_is_recovered_from_stage_moves(rotation: float, scale: float) -> None:
    sem = SimulatedSEM(FoldedSurface(seed=4), noise=0.03, seed=2)
    geometry = SEMGeometry(rotation=rotation, scale=scale, offset=(1e-6, -2e-6))
    reference = _frame(sem, geometry, (0.0, 0.0))
    moves = [(2e-6, 0.0), (-2e-6, 0.0), (0.0, 2e-6), (0.0, -2e-6), (4e-6, 0.0), (0.0, 4e-6)]
    moved = [(m, _frame(sem, geometry, m)) for m in moves]
    centre = ((PIXELS - 1) / 2, (PIXELS - 1) / 2)  # the field's centre: at the offset
    found = calibrate(reference, moved, anchor=(centre, geometry.offset), field=FIELD)
    assert found.rotation_deg == pytest.approx(rotation, abs=0.05)
    assert found.scale[0] == pytest.approx(scale * PITCH, rel=1e-3)
    assert found.scale[1] == pytest.approx(scale * PITCH, rel=1e-3)
    assert abs(found.shear) < 2e-3 and found.mirrored and found.residual_px < 0.2
    np.testing.assert_allclose(found.matrix, _truth(geometry), rtol=0, atol=2e-3 * PITCH)
    # every pixel where the truth has it, within a pixel, also after a stage move
    for column, row in ((0.0, 0.0), (255.0, 0.0), (100.0, 200.0)):
        x, y = found.to_stage(column, row, at=(5e-6, 3e-6))
        a = np.deg2rad(rotation)
        u, v = (column - centre[0]) * PITCH, -(row - centre[1]) * PITCH
        tx = geometry.offset[0] + scale * (np.cos(a) * u - np.sin(a) * v) - 5e-6
        ty = geometry.offset[1] + scale * (np.sin(a) * u + np.cos(a) * v) - 3e-6
        assert np.hypot(x - tx, y - ty) < PITCH
        assert found.to_pixel(x, y, at=(5e-6, 3e-6)) == pytest.approx((column, row), abs=1e-6)


def test_a_calibration_that_cannot_be_trusted_is_refused_with_why() -> None:
    geometry = SEMGeometry(rotation=2.0, scale=1.0)
    anchor = ((0.0, 0.0), (0.0, 0.0))
    flat = SimulatedSEM(Chessboard(step=0.0, roughness=0.0), noise=0.05, seed=3)  # nothing
    reference = _frame(flat, geometry, (0.0, 0.0))
    moved = [(m, _frame(flat, geometry, m)) for m in ((2e-6, 0.0), (0.0, 2e-6))]
    with pytest.raises(CalibrationError, match="too little structure"):
        calibrate(reference, moved, anchor=anchor)
    sem = SimulatedSEM(FoldedSurface(seed=4), noise=0.03, seed=2)
    reference = _frame(sem, geometry, (0.0, 0.0))
    still = [((2e-6, 0.0), _frame(sem, geometry, (0.0, 0.0))), ((0.0, 2e-6), reference)]
    with pytest.raises(CalibrationError, match="did not move"):
        calibrate(reference, still, anchor=anchor)
    wrong = [  # the stage went 3 µm where it was told 2
        ((2e-6, 0.0), _frame(sem, geometry, (2e-6, 0.0))),
        ((0.0, 2e-6), _frame(sem, geometry, (0.0, 2e-6))),
        ((0.0, -2e-6), _frame(sem, geometry, (0.0, -2e-6))),
        ((-2e-6, 0.0), _frame(sem, geometry, (-3e-6, 0.0))),
        ((4e-6, 0.0), _frame(sem, geometry, (4e-6, 0.0))),
    ]
    with pytest.raises(CalibrationError, match="disagree"):
        calibrate(reference, wrong, anchor=anchor)
    one_way = [(m, _frame(sem, geometry, m)) for m in ((2e-6, 0.0), (4e-6, 0.0))]
    with pytest.raises(CalibrationError, match="two directions"):
        calibrate(reference, one_way, anchor=anchor)


def test_drift_and_the_stages_sensor_errors_are_taken_out() -> None:
    """Frames back at the start measure the charging drift (a random walk of 15 nm a frame);
    the fitted constant takes the sensor's error at the start; moves of many lengths average
    its periodic error at their ends: the map within the issue's bounds all the same."""
    sem = SimulatedSEM(FoldedSurface(seed=5, tile=20.48e-6), noise=0.03, seed=4)
    geometry = SEMGeometry(rotation=3.0, scale=1.025)
    rng = np.random.default_rng(7)
    start = (1.3e-6, -0.7e-6)

    def sensor(x: float) -> float:  # an encoder's periodic error, 25 nm over 4 µm
        return x + 25e-9 * np.sin(2 * np.pi * x / 4e-6)

    drift = np.zeros(2)

    def frame(at: tuple[float, float]) -> np.ndarray:
        drift[:] += rng.normal(0.0, 15e-9, 2)  # charging: a random walk, 15 nm a frame
        shifted = replace(geometry, offset=(drift[0], drift[1]))
        return _frame(sem, shifted, at, pixels=128)

    step = FIELD / 12
    reference = frame(start)
    moved, returned = [], []
    for k in range(1, 7):
        for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            at = (start[0] + k * step * sx, start[1] + k * step * sy)
            read = (sensor(at[0]) - sensor(start[0]), sensor(at[1]) - sensor(start[1]))
            moved.append((read, frame(at)))
            returned.append(frame(start))
    anchor = ((63.5, 63.5), (-start[0], -start[1]))  # 128 px frames: a quarter the work
    found = calibrate(reference, moved, anchor=anchor, field=FIELD, returned=returned)
    assert found.rotation_deg == pytest.approx(3.0, abs=0.05)
    assert found.scale == pytest.approx((2.05 * PITCH, 2.05 * PITCH), rel=1e-3)
    # what the returns measured: the walk the frames took (a pixel and more by the end)
    assert np.hypot(*drift) > PITCH


def test_the_returns_refuse_a_sample_that_drifts_too_fast() -> None:
    sem = SimulatedSEM(FoldedSurface(seed=5), noise=0.03, seed=4)
    geometry = SEMGeometry(rotation=1.0, scale=1.0)
    moves = [(2e-6, 0.0), (-2e-6, 0.0), (0.0, 2e-6), (0.0, -2e-6)]
    moved = [(m, _frame(sem, geometry, m)) for m in moves]
    reference = _frame(sem, geometry, (0.0, 0.0))
    away = [_frame(sem, geometry, (k * 0.4e-6, 0.0)) for k in range(1, 5)]  # 5 px a frame
    with pytest.raises(CalibrationError, match="drifts"):
        calibrate(reference, moved, anchor=((0.0, 0.0), (0.0, 0.0)), returned=away)
