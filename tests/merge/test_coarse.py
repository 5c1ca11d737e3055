import numpy as np

from merge.coarse import coarse_start, signal_information
from merge.overlap import overlapping_pairs
from tests.conftest import Synthetic


def test_coarse_start_finds_xy_and_the_z_staircase(small_mosaic: Synthetic) -> None:
    patches = small_mosaic.patch_set.patches
    boxes = np.array([p.footprint for p in patches])
    pairs = overlapping_pairs(boxes, margin=2e-7)
    start = coarse_start(patches, pairs, cell=2e-8, max_shift=3e-7)
    centre = np.array([[*p.center, float(np.nanmedian(p.heights))] for p in patches])
    truth = np.array(
        [
            s.rotation @ c + s.translation - c
            for s, c in zip(small_mosaic.synth, centre, strict=True)
        ]
    )
    err = start.translation - truth
    err -= err.mean(axis=0)  # the gauge
    assert np.abs(err[:, :2]).max() < 15e-9  # within a cell or so: a start, not the answer
    assert np.abs(err[:, 2]).max() < 5e-9
    assert start.xy_measured.all()


def test_noise_is_not_counted_as_texture() -> None:
    tensor = np.diag([10.0, 3.0])
    out = signal_information(tensor, 4.0)
    np.testing.assert_allclose(out, np.diag([6.0, 0.0]))


def test_overlapping_pairs_are_found_by_footprint() -> None:
    boxes = np.array([[0, 0, 1, 1], [0.9, 0, 2, 1], [3, 0, 4, 1]], dtype=float)
    assert overlapping_pairs(boxes).tolist() == [[0, 1]]
    assert overlapping_pairs(boxes, margin=0.6).tolist() == [[0, 1], [1, 2]]
