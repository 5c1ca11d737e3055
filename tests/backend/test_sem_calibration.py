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


def _frame(sem: SimulatedSEM, geometry: SEMGeometry, stage: tuple[float, float]) -> np.ndarray:
    """The SEM's image with the sample stage at ``stage``: it shows sample point
    ``lab - stage`` at the lab point a pixel looks at."""
    ox, oy = geometry.offset
    moved = replace(geometry, offset=(ox - stage[0], oy - stage[1]))
    return render_frame(sem, moved, field=FIELD, pixels=PIXELS)


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
        ((-2e-6, 0.0), _frame(sem, geometry, (-3e-6, 0.0))),
    ]
    with pytest.raises(CalibrationError, match="disagree"):
        calibrate(reference, wrong, anchor=anchor)
    one_way = [(m, _frame(sem, geometry, m)) for m in ((2e-6, 0.0), (4e-6, 0.0))]
    with pytest.raises(CalibrationError, match="two directions"):
        calibrate(reference, one_way, anchor=anchor)
