from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backend.acquisition.planner import PatchSpec, PlanError, Roi, plan_mosaic
from hardware.protocols import SEMImage


def test_grid_counts_and_snake_order() -> None:
    # 0.6 x 1.2 µm patches stepping 0.3 and 0.8 µm: 3.0 µm needs 9 columns (0.6 + 8 x 0.3)
    # and 4 rows (1.2 + 2 x 0.8 = 2.8 falls short of 3.0)
    plan = plan_mosaic(Roi(0, 0, 3.0e-6, 3.0e-6), PatchSpec(0.6e-6, 1.2e-6, (30, 60)), (0.5, 1 / 3))
    assert (plan.rows, plan.cols) == (4, 9)
    plan = plan_mosaic(Roi(0, 0, 3.3e-6, 3.6e-6), PatchSpec(0.6e-6, 1.2e-6, (30, 60)), (0.5, 1 / 3))
    assert (plan.rows, plan.cols) == (4, 10)
    assert [(p.row, p.col) for p in plan.patches[9:12]] == [(0, 9), (1, 9), (1, 8)]  # snake
    assert plan.patch.pixel_size == pytest.approx((20e-9, 20e-9))


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0.1e-6, 30e-6),
    st.floats(0.1e-6, 30e-6),
    st.floats(0.2e-6, 1.6e-6),
    st.floats(0.2e-6, 1.6e-6),
    st.floats(0.0, 0.89),
    st.floats(0.0, 0.89),
)
def test_the_grid_covers_the_roi_centred(
    w: float, h: float, pw: float, ph: float, ox: float, oy: float
) -> None:
    roi = Roi(-w / 2 + 1e-6, -h / 2, w, h)
    refused: PlanError | None = None
    try:
        plan = plan_mosaic(roi, PatchSpec(pw, ph, (32, 32)), (ox, oy))
    except PlanError as exc:
        refused = exc
    if refused is not None:
        # only too many patches, or an overlap of fewer than 3 pixels, can refuse these
        assert refused.field == "roi" or (refused.field == "overlap" and min(ox, oy) * 32 < 3)
        return
    x0, y0, x1, y1 = plan.extent
    assert x0 <= roi.x + 1e-15 and x1 >= roi.x + roi.width - 1e-15
    assert y0 <= roi.y + 1e-15 and y1 >= roi.y + roi.height - 1e-15
    assert (x0 + x1) / 2 == pytest.approx(roi.x + roi.width / 2, abs=1e-12)
    assert len(plan.patches) == plan.rows * plan.cols
    assert sorted(p.index for p in plan.patches) == list(range(len(plan.patches)))


@pytest.mark.parametrize(
    ("roi", "patch", "overlap", "field"),
    [
        (Roi(0, 0, 0, 1e-6), PatchSpec(1e-6, 1e-6, (32, 32)), (0.3, 0.3), "roi.width"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(2e-6, 1e-6, (32, 32)), (0.3, 0.3), "patch.width"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(1e-6, -1.0, (32, 32)), (0.3, 0.3), "patch.height"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(1e-6, 1e-6, (4, 32)), (0.3, 0.3), "patch.pixels"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(1e-6, 1e-6, (32, 5000)), (0.3, 0.3), "patch.pixels"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(1e-6, 1e-6, (32, 32)), (0.9, 0.3), "overlap"),
        (Roi(0, 0, 1e-6, 1e-6), PatchSpec(1e-6, 1e-6, (32, 32)), (-0.1, 0.3), "overlap"),
        (Roi(5.9e-3, 0, 1e-3, 1e-6), PatchSpec(1e-6, 1e-6, (32, 32)), (0.3, 0.3), "roi"),
        (Roi(0, 0, 1e-3, 1e-3), PatchSpec(1e-6, 1e-6, (32, 32)), (0.3, 0.3), "roi"),
        (Roi(float("nan"), 0, 1e-6, 1e-6), PatchSpec(1e-6, 1e-6, (32, 32)), (0.3, 0.3), "roi.x"),
    ],
)
def test_bad_plans_name_the_field(
    roi: Roi, patch: PatchSpec, overlap: tuple[float, float], field: str
) -> None:
    with pytest.raises(PlanError) as err:
        plan_mosaic(roi, patch, overlap)
    assert err.value.field == field
    assert str(err.value).startswith(field)


def test_roi_from_sem_pixels_through_the_calibration() -> None:
    img = SEMImage(pixels=np.zeros((100, 100)), origin=(1e-6, 2e-6), pixel_size=(10e-9, 10e-9))
    roi = Roi.from_sem(img, 10, 20, 50, 30)
    assert (roi.x, roi.y, roi.width, roi.height) == pytest.approx((1.1e-6, 2.2e-6, 0.5e-6, 0.3e-6))


def test_a_roi_drawn_on_a_rotated_sem_image_covers_the_rotated_rectangle() -> None:
    a = np.deg2rad(30.0)
    p = 10e-9
    matrix = ((p * np.cos(a), p * np.sin(a)), (p * np.sin(a), -p * np.cos(a)))  # rows down
    img = SEMImage(np.zeros((100, 100)), (1e-6, 2e-6), (p, p), matrix)
    roi = Roi.from_sem(img, 0, 0, 40, 20)
    corners = [img.to_stage(c, r) for c in (0, 40) for r in (0, 20)]
    assert roi.x == pytest.approx(min(x for x, _ in corners))
    assert roi.y == pytest.approx(min(y for _, y in corners))
    # a 400 x 200 nm rectangle turned by 30°: its stage-aligned cover
    assert roi.width == pytest.approx(400e-9 * np.cos(a) + 200e-9 * np.sin(a))
    assert roi.height == pytest.approx(400e-9 * np.sin(a) + 200e-9 * np.cos(a))
    assert img.to_pixel(*img.to_stage(12.5, 7.25)) == pytest.approx((12.5, 7.25))
