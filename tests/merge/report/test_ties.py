"""Which patches a chain of overlaps that measured them ties to the mosaic, axis by axis."""

from __future__ import annotations

import numpy as np

from backend.synthetic import patch_set_from_synth
from hardware.sim.surfaces import Chessboard
from merge import PatchTransform, run
from merge.report import ties
from merge.report.ties import untied
from tests.conftest import make_synthetic, narrow_paper_grid, still

#: A grating's flat face (1.5 nm of roughness at a pixel's scale) without any drift.
STILL = still(0.5e-9)
#: The start's information of a pair measured both ways, and of one measured along y only.
BOTH = np.eye(2) * 2.5e15
ONLY_Y = np.diag([0.0, 2.5e15])


def _row_of_three() -> list:
    syn = make_synthetic(Chessboard(step=0.0, seed=5), rows=1, cols=3, drift=STILL, pixels=(30, 30))
    return list(syn.patch_set)


def test_a_block_the_start_measured_along_y_only_is_tied_along_x_where_its_texture_agrees() -> None:
    patches = _row_of_three()
    pairs = np.array([[0, 1], [1, 2]])
    info = np.stack([BOTH, ONLY_Y])
    # at the truth the roughness of the second overlap confirms x: one block
    truth = [PatchTransform() for _ in patches]
    assert untied(patches, truth, pairs, info) == {}
    # six pixels off along x its roughness no longer agrees: the last patch is not tied in x
    off = [PatchTransform(), PatchTransform(), PatchTransform(t=np.array([1.6e-7, 0.0, 0.0]))]
    assert untied(patches, off, pairs, info) == {2: ("x",)}
    # measured both ways, the start's own measurement ties it whatever the texture says
    assert untied(patches, off, pairs, np.stack([BOTH, BOTH])) == {}


def test_nothing_measured_and_no_overlap_left_ties_nothing() -> None:
    patches = _row_of_three()
    apart = [PatchTransform(t=np.array([3e-6 * k, 0.0, 0.0])) for k in range(3)]
    loose = untied(patches, apart, np.array([[0, 1], [1, 2]]), np.zeros((2, 2, 2)))
    # three blocks of one: the largest is the first, the others are loose every way
    every = ("x", "y", "x = y", "x = -y")
    assert loose == {1: every, 2: every}


def test_narrow_overlaps_no_longer_claim_a_block_they_do_not_tie() -> None:
    # 15 % overlaps of 30 x 60 px chessboard patches at the paper's grid: the start measured
    # no pair between columns 6 and 7 along x; the refinement kept the three right columns
    # 120 nm off the seven left ones, and every patch claimed 2 nm
    synth = narrow_paper_grid(Chessboard(seed=102001), 102001)
    result = run(patch_set_from_synth(synth))
    loose = {p.id for p in result.patches if not p.xy_constrained}
    assert {s.id for s in synth if s.col >= 7} <= loose
    assert any("no chain of overlaps" in w for w in result.warnings)


def test_each_overlap_group_keeps_its_own_largest_block() -> None:
    group = np.array([0, 0, 0, 1, 1, 2])
    label = np.array([5, 5, 7, 2, 3, 4])
    # group 0: block 5 is the largest; group 1: a tie, the first block; group 2: alone
    np.testing.assert_array_equal(
        ties._outside_largest(label, group), [False, False, True, False, True, False]
    )
