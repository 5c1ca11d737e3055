"""Two fits compared on the points both overlap (:mod:`merge.report.common_points`)."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.sim.surfaces import FoldedSurface
from merge import PatchTransform
from merge.core.overlap import overlapping_pairs
from merge.refine.bank import SurfaceBank
from merge.report.common_points import CommonMisfit, common_misfit
from tests.conftest import Synthetic, make_synthetic, still

NOISE = 1e-9


@pytest.fixture(scope="module")
def truth_placed(folded: FoldedSurface) -> Synthetic:
    """2 x 3 patches without drift: the nominal placement is the truth."""
    return make_synthetic(folded, drift=still(NOISE))


def _compare(
    mosaic: Synthetic, before: list[PatchTransform], after: list[PatchTransform]
) -> CommonMisfit:
    patches = list(mosaic.patch_set)
    scale = min(patches[0].pixel_size)
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=0.5e-6)
    return common_misfit(SurfaceBank(patches, scale, 0.0, 1), pairs, before, after, scale=scale)


def _moved(n: int, c: int, shift: tuple[float, float]) -> list[PatchTransform]:
    """Every patch at the truth but patch ``c``, moved by ``shift`` (metres)."""
    out = [PatchTransform() for _ in range(n)]
    out[c] = PatchTransform(t=np.array([shift[0], shift[1], 0.0]))
    return out


def test_the_truth_explains_the_common_points_better_than_a_patch_moved_off_it(
    truth_placed: Synthetic,
) -> None:
    n = len(truth_placed.synth)
    truth, wrong = _moved(n, 1, (0.0, 0.0)), _moved(n, 1, (40e-9, -30e-9))
    better = _compare(truth_placed, wrong, truth)
    assert better.points > 1000
    assert better.ratio < 0.9 and better.evidence > 0.1 * better.points
    worse = _compare(truth_placed, truth, wrong)
    assert worse.ratio > 1.1 and worse.evidence < 0
    same = _compare(truth_placed, truth, truth)
    assert same.ratio == pytest.approx(1.0) and same.evidence == pytest.approx(0.0)


def test_points_only_one_fit_overlaps_do_not_count(truth_placed: Synthetic) -> None:
    n = len(truth_placed.synth)
    misplaced = _moved(n, 1, (40e-9, -30e-9))
    # patch 1 (top middle) carried far off its neighbours: its misfit is shed, not mended
    away = _moved(n, 1, (0.0, 5e-6))
    carried = _compare(truth_placed, misplaced, away)
    alone = _compare(truth_placed, misplaced, misplaced)
    assert carried.points < alone.points
    # on the points both fits overlap (the other patches' own pairs) they are the same fit
    assert carried.ratio == pytest.approx(1.0, abs=1e-9)
    assert carried.evidence == pytest.approx(0.0, abs=1e-6)


def test_fits_of_other_patches_are_refused(truth_placed: Synthetic) -> None:
    n = len(truth_placed.synth)
    with pytest.raises(ValueError, match="two fits of 6 patches"):
        _compare(truth_placed, _moved(n, 0, (0.0, 0.0)), _moved(n - 1, 0, (0.0, 0.0)))
