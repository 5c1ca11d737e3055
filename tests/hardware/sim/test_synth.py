import numpy as np
import pytest

from hardware.mosaic_plan import snake_grid
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from hardware.sim.synth import scan_fraction, synthesize, true_points


def test_snake_order_visits_rows_back_and_forth() -> None:
    plan = snake_grid(2, 3, patch_size=(1.0, 2.0), overlap=(0.5, 0.25))
    assert [(p.row, p.col) for p in plan] == [(0, 0), (0, 1), (0, 2), (1, 2), (1, 1), (1, 0)]
    assert plan[1].origin == pytest.approx((0.5, 0.0))
    assert plan[3].origin == pytest.approx((1.0, 1.5))
    with pytest.raises(ValueError, match="overlaps"):
        snake_grid(2, 2, patch_size=(1.0, 1.0), overlap=(1.0, 0.0))


def test_without_errors_patches_sample_the_surface(folded: FoldedSurface) -> None:
    none = DriftModel(0, 0, 0, 0, 0, 0, 0)
    synth = synthesize(
        folded,
        rows=1,
        cols=2,
        patch_size=(4e-7, 4e-7),
        pixels=(20, 20),
        overlap=(0.5, 0.0),
        drift=none,
    )
    s = synth[1]
    xx, yy = np.meshgrid(s.origin[0] + np.arange(20) * 2e-8, s.origin[1] + np.arange(20) * 2e-8)
    np.testing.assert_allclose(s.heights, folded.height(xx, yy), atol=1e-15)


def test_truth_maps_measured_points_back_onto_the_surface(folded: FoldedSurface) -> None:
    model = DriftModel(noise=0.0, line_noise=0.0, z_drift_sigma=5e-9)
    synth = synthesize(
        folded,
        rows=2,
        cols=2,
        patch_size=(4e-7, 4e-7),
        pixels=(20, 20),
        overlap=(0.3, 0.3),
        drift=model,
        seed=5,
    )
    offsets = [s.translation[2] for s in synth]
    assert len(set(np.round(offsets, 15))) == 4  # a staircase: every patch its own Z offset
    for s in synth:
        q = true_points(s)
        np.testing.assert_allclose(q[..., 2], folded.height(q[..., 0], q[..., 1]), atol=1e-14)


def test_same_seed_same_set(folded: FoldedSurface) -> None:
    a = synthesize(
        folded, rows=1, cols=2, patch_size=(4e-7, 4e-7), pixels=(10, 10), overlap=(0.3, 0), seed=9
    )
    b = synthesize(
        folded, rows=1, cols=2, patch_size=(4e-7, 4e-7), pixels=(10, 10), overlap=(0.3, 0), seed=9
    )
    np.testing.assert_array_equal(a[1].heights, b[1].heights)
    frac = scan_fraction((2, 3))
    assert frac[0, 0] == 0 and frac[1, 0] == pytest.approx(0.5)
