"""The live merge: patches added one by one end where the batch merge ends, each addition
moves only its neighbourhood, and its canvas is the render."""

from __future__ import annotations

import numpy as np
import pytest

from backend.synthetic import registration_error
from hardware.sim.surfaces import Chessboard, FoldedSurface
from merge import MergeConfig, render_mosaic, run
from merge.live import LiveMerge
from merge.pipeline import PERIODIC
from tests.conftest import Synthetic, make_synthetic, stripes_mosaic


def _in_scan_order(live: LiveMerge, mosaic: Synthetic) -> None:
    for p in sorted(mosaic.patch_set.patches, key=lambda p: p.order):
        live.add(p)


def _transforms_of(live: LiveMerge, mosaic: Synthetic) -> list:
    by_id = dict(zip(live.ids, live.transforms, strict=True))
    return [by_id[p.id] for p in mosaic.patch_set.patches]


@pytest.mark.parametrize("surface", [FoldedSurface(seed=7), Chessboard(seed=3)])
def test_patches_added_one_by_one_end_where_the_batch_merge_ends(surface: object) -> None:
    mosaic = make_synthetic(surface, rows=3, cols=3, seed=4, pixels=(48, 48))  # type: ignore[arg-type]
    batch = run(mosaic.patch_set)
    live = LiveMerge()
    _in_scan_order(live, mosaic)
    before = registration_error(mosaic.synth, _transforms_of(live, mosaic))
    result = live.result()
    after = registration_error(mosaic.synth, _transforms_of(live, mosaic))
    reference = registration_error(mosaic.synth, batch.transforms)
    # already near the floor while it grew (never a chain that drifts), and at the end the
    # batch merge's solution within a small fraction of the noise (1 nm)
    assert before[0] < reference[0] + 1e-9 and before[1] < reference[1] + 1e-9
    assert abs(after[0] - reference[0]) < 0.1e-9 and abs(after[1] - reference[1]) < 0.1e-9
    assert len(result.patches) == 9 and result.method == "default"
    assert np.isfinite(result.mosaic.heights).mean() > 0.85  # corners of rotated patches


def test_a_live_mosaic_of_a_periodic_sample_says_so_as_the_batch_merge_does(
    small_mosaic: Synthetic,
) -> None:
    for mosaic, periodic in ((stripes_mosaic(), True), (small_mosaic, False)):
        live = LiveMerge()
        _in_scan_order(live, mosaic)
        said = [w for w in live.result().warnings if w.startswith(PERIODIC)]
        assert len(said) == int(periodic)


def test_an_addition_moves_only_the_neighbourhood_it_touches(folded: FoldedSurface) -> None:
    strip = make_synthetic(folded, rows=1, cols=6, seed=2, pixels=(32, 32))
    live = LiveMerge()
    patches = sorted(strip.patch_set.patches, key=lambda p: p.order)
    for p in patches[:5]:
        live.add(p)
    before = [tr.t.copy() for tr in live.transforms]
    update = live.add(patches[5])
    moved = [
        float(np.abs(tr.t - t0).max()) for tr, t0 in zip(live.transforms, before, strict=False)
    ]
    assert patches[4].id in update.neighbours and patches[0].id not in update.neighbours
    assert moved[0] == 0.0  # far away: held, not even touched
    assert update.fits[patches[5].id].correspondences > 0
    assert set(update.seconds) == {"start", "refine", "report", "render"}


def test_a_patch_added_again_replaces_itself(small_mosaic: Synthetic) -> None:
    live = LiveMerge()
    _in_scan_order(live, small_mosaic)
    again = small_mosaic.patch_set.patches[2]
    live.add(again)
    assert len(live) == len(small_mosaic.patch_set)
    assert live.ids[-1] == again.id and live.ids.count(again.id) == 1
    live.remove(again.id)
    assert again.id not in live.ids and len(live) == len(small_mosaic.patch_set) - 1


def test_the_live_canvas_is_the_render_of_the_current_transforms(small_mosaic: Synthetic) -> None:
    live = LiveMerge()
    _in_scan_order(live, small_mosaic)
    live.remove(small_mosaic.patch_set.patches[0].id)  # a share taken out as well
    mosaic = live.mosaic()  # cut to the patches' extent on the canvas's lattice
    (x0, y0), (dx, dy) = mosaic.origin, mosaic.pixel_size
    ny, nx = mosaic.heights.shape
    bounds = (x0, y0, x0 + (nx - 1) * dx, y0 + (ny - 1) * dy)
    reference = render_mosaic(live.patches, live.transforms, pixel_size=(dx, dy), bounds=bounds)
    np.testing.assert_array_equal(np.isfinite(mosaic.heights), np.isfinite(reference.heights))
    both = np.isfinite(reference.heights)
    np.testing.assert_allclose(mosaic.heights[both], reference.heights[both], atol=1e-15)
    np.testing.assert_array_equal(mosaic.coverage, reference.coverage)


def test_a_cancelled_polish_leaves_the_mosaic_as_it_was(small_mosaic: Synthetic) -> None:
    live = LiveMerge(full_every=2)
    assert not live.polish()  # nothing due on an empty merge
    _in_scan_order(live, small_mosaic)
    assert live.full_due
    before = [tr.t.copy() for tr in live.transforms]
    assert not live.polish(cancel=lambda: True)
    assert all(np.array_equal(tr.t, t0) for tr, t0 in zip(live.transforms, before, strict=True))
    assert live.polish() and not live.full_due


def test_bad_options_are_refused() -> None:
    with pytest.raises(ValueError, match="default method"):
        LiveMerge(MergeConfig(method="paper"))
    with pytest.raises(ValueError, match="full_every"):
        LiveMerge(full_every=0)
    with pytest.raises(ValueError, match="no patch"):
        LiveMerge().mosaic()
    with pytest.raises(ValueError, match="at least 2"):
        LiveMerge().result()
