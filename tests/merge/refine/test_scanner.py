"""The scanner's shared bend: measured from the overlaps, taken out, merged again."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray

from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from merge import MergeConfig, Patch, PatchSet, run
from merge.io.result import result_document
from merge.refine.scanner import ScanDistortion, estimate_distortion, undistort
from tests.conftest import Synthetic, make_synthetic

FloatArray = NDArray[np.float64]

PIXELS = (32, 48)


def _bend(n: int, *, bow: float, creep: float) -> FloatArray:
    """An open-loop piezo's displacement over ``n`` lines, metres: a hysteresis bow (a
    parabola) and the creep of the move back to the first line (dying away)."""
    f = np.linspace(0.0, 1.0, n)
    return -bow * 4 * f * (1 - f) - creep * np.exp(-f * n / 12.0)


def _shape(v: FloatArray) -> FloatArray:
    """``v`` without its mean and linear part (overlaps do not see those)."""
    i = np.arange(len(v), dtype=np.float64)
    line = np.polynomial.Polynomial.fit(i, v, 1)(i)
    out: FloatArray = v - line
    return out


@pytest.fixture(scope="module")
def bent() -> tuple[Synthetic, FloatArray, FloatArray]:
    # without the offset and scale that overlaps cannot see (and no merge could tell)
    cols = _shape(_bend(PIXELS[0], bow=2e-9, creep=0.0))
    rows = _shape(_bend(PIXELS[1], bow=6e-9, creep=5e-9))
    mosaic = make_synthetic(
        FoldedSurface(seed=3),
        rows=3,
        cols=4,
        pixels=PIXELS,
        patch_size=(0.6e-6, 0.9e-6),
        overlap=(0.5, 1 / 3),
        drift=DriftModel(noise=0.3e-9, line_noise=0.1e-9),
        seed=2,
        bend=(cols, rows),
    )
    return mosaic, cols, rows


def test_the_bend_of_rows_and_columns_is_recovered_from_the_overlaps(
    bent: tuple[Synthetic, FloatArray, FloatArray],
) -> None:
    mosaic, cols, rows = bent
    first = run(mosaic.patch_set)
    d = estimate_distortion(mosaic.patch_set.patches, first.transforms)
    assert d is not None
    assert d.rows.shape == (PIXELS[1],) and d.cols.shape == (PIXELS[0],)
    error_rows = np.sqrt(np.mean((_shape(d.rows) - _shape(rows)) ** 2))
    error_cols = np.sqrt(np.mean((_shape(d.cols) - _shape(cols)) ** 2))
    assert np.ptp(_shape(rows)) > 4e-9  # what there was to find
    assert d.significant == (True, True)
    assert error_rows < 0.15 * np.ptp(_shape(rows)), error_rows
    assert error_cols < 0.5e-9, error_cols
    assert d.observations[0] > 100 and d.observations[1] > 100
    assert np.all(d.rows_sigma < 0.5e-9)


def test_self_calibration_registers_a_bent_mosaic_better(
    bent: tuple[Synthetic, FloatArray, FloatArray],
) -> None:
    mosaic = bent[0]
    rigid = run(mosaic.patch_set)
    steps: list[int] = []
    calibrated = run(
        mosaic.patch_set, MergeConfig(self_calibrate=True), progress=lambda i, r: steps.append(i)
    )
    assert steps == list(range(1, len(steps) + 1))  # one count over both merges
    assert len(steps) > calibrated.iterations
    xy_rigid, z_rigid = mosaic.registration_error(rigid.transforms)
    xy, z = mosaic.registration_error(calibrated.transforms)
    assert calibrated.distortion is not None and rigid.distortion is None
    assert xy < 0.7 * xy_rigid and z < z_rigid, (xy, xy_rigid, z, z_rigid)
    assert {"first_merge", "self_calibration"} <= set(calibrated.timings)
    doc = result_document(calibrated, mosaic.patch_set)
    assert doc["parameters"]["self_calibrate"] is True
    assert len(doc["scan_distortion"]["rows"]) == PIXELS[1]
    assert doc["scan_distortion"]["peak_to_valley"][1] > 3e-9


def test_a_straight_scanner_is_found_straight(small_mosaic: Synthetic) -> None:
    first = run(small_mosaic.patch_set)
    d = estimate_distortion(small_mosaic.patch_set.patches, first.transforms)
    assert d is not None
    assert d.significant == (False, False)
    assert not d.rows.any() and not d.cols.any()
    assert np.all(d.rows_sigma < 0.5e-9)
    calibrated = run(small_mosaic.patch_set, MergeConfig(self_calibrate=True))
    # no second merge: the first stands, with the (absent) bend on record
    assert calibrated.distortion is not None and "first_merge" not in calibrated.timings
    np.testing.assert_array_equal(calibrated.mosaic.heights, first.mosaic.heights)


def test_undistort_puts_a_bent_ramp_back_on_its_nominal_rows() -> None:
    ny, nx = 40, 8
    dy = 20e-9
    rows = _bend(ny, bow=8e-9, creep=4e-9)
    cols = np.zeros(nx)
    y_seen = np.arange(ny) * dy + rows  # where each row really looked
    patch = Patch("a", np.repeat(0.01 * y_seen[:, None], nx, axis=1), (0.0, 0.0), (dy, dy))
    d = ScanDistortion(rows, cols, np.zeros(ny), np.zeros(nx), (0, 0))
    out = undistort(patch, d).heights
    inside = np.isfinite(out[:, 0])
    assert inside.sum() >= ny - 1  # at most a row lost at an end the bend pulled in
    expected = 0.01 * np.arange(ny) * dy
    np.testing.assert_allclose(out[inside, 0], expected[inside], atol=0.01 * 0.2e-9)


@settings(max_examples=30, deadline=None)
@given(arrays(np.float64, (6, 5), elements=st.floats(-1e-6, 1e-6)))
def test_no_bend_leaves_every_height_as_it_was(heights: FloatArray) -> None:
    patch = Patch("a", heights, (0.0, 0.0), (1e-8, 1e-8))
    d = ScanDistortion(np.zeros(6), np.zeros(5), np.zeros(6), np.zeros(5), (0, 0))
    np.testing.assert_array_equal(undistort(patch, d).heights, heights)


def test_scans_of_different_sizes_have_no_one_bend(small_mosaic: Synthetic) -> None:
    patches = list(small_mosaic.patch_set.patches)
    p = patches[0]
    patches[0] = Patch(p.id, p.heights[:-2], p.origin, p.pixel_size, order=p.order)
    first = run(PatchSet(patches))
    assert estimate_distortion(patches, first.transforms) is None
    result = run(PatchSet(patches), MergeConfig(self_calibrate=True))
    assert result.distortion is None
    assert any("self-calibration needs scans of one size" in w for w in result.warnings)


def test_bad_arguments_are_value_errors(small_mosaic: Synthetic) -> None:
    patches = small_mosaic.patch_set.patches
    transforms = run(small_mosaic.patch_set, MergeConfig(method="nominal")).transforms
    with pytest.raises(ValueError, match="degree"):
        estimate_distortion(patches, transforms, degree=1)
    with pytest.raises(ValueError, match="transforms"):
        estimate_distortion(patches, transforms[:-1])
    with pytest.raises(ValueError, match="default method"):
        MergeConfig(method="paper", self_calibrate=True)
    d = ScanDistortion(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), (0, 0))
    with pytest.raises(ValueError, match="3 x 3 px"):
        undistort(patches[0], d)
