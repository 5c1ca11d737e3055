"""A patch's neighbourhood in the live merge: who it can overlap, who its start places and who
holds the frame, and its pairs renumbered."""

from __future__ import annotations

import numpy as np
import pytest

from merge.live.neighbourhood import nominal_neighbours, to_place, within


def _grid_boxes(rows: int, cols: int, side: float, step: float) -> np.ndarray:
    """Nominal boxes (x0, y0, x1, y1) of a rows x cols grid of square patches, row-major."""
    return np.array(
        [
            [c * step, r * step, c * step + side, r * step + side]
            for r in range(rows)
            for c in range(cols)
        ]
    )


def test_nominal_neighbours_are_those_within_reach_of_the_stage_error() -> None:
    boxes = _grid_boxes(3, 3, side=1.0, step=0.8)  # 20 % overlap: the 8 around the centre
    assert nominal_neighbours(boxes, 4, 0.0).tolist() == [0, 1, 2, 3, 5, 6, 7, 8]
    # a corner patch meets its 3 neighbours; patches two steps off stay out of reach ...
    assert nominal_neighbours(boxes, 0, 0.0).tolist() == [1, 3, 4]
    # ... until the stage's error could bring them over it (two steps = 1.6, side 1.0)
    assert nominal_neighbours(boxes, 0, 0.55).tolist() == [1, 3, 4]
    assert nominal_neighbours(boxes, 0, 0.65).tolist() == [1, 2, 3, 4, 5, 6, 7, 8]


def test_a_lone_patch_has_no_neighbours() -> None:
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [5.0, 5.0, 6.0, 6.0]])
    assert nominal_neighbours(boxes, 0, 1.0).size == 0


def test_the_new_patch_is_placed_and_known_neighbours_hold_the_frame() -> None:
    # neighbours: known both ways, known both ways, measured along one axis before and now both
    complete = np.array([True, True, True, True])
    known = np.array([True, True, False, False])
    moving, reference = to_place(complete, known)
    assert moving.tolist() == [False, False, True, True]
    assert reference.tolist() == [True, True, False, False]


def test_where_no_known_neighbour_would_stay_none_moves_but_the_new_patch() -> None:
    # no neighbour was measured both ways before: all of them hold the frame as they are
    moving, reference = to_place(np.array([True, True, True]), np.array([False, False, True]))
    assert moving.tolist() == [False, False, True]
    assert reference.tolist() == [True, True, False]


def test_an_edge_neighbour_this_start_cannot_measure_either_stays() -> None:
    moving, reference = to_place(np.array([True, False, False]), np.array([True, False, False]))
    assert moving.tolist() == [False, False, True]
    assert reference.tolist() == [True, False, False]


def test_to_place_rejects_arrays_of_other_shapes() -> None:
    with pytest.raises(ValueError, match="two"):
        to_place(np.array([True, False]), np.array([True]))
    with pytest.raises(ValueError, match="two"):
        to_place(np.zeros(0, dtype=bool), np.zeros(0, dtype=bool))


def test_within_keeps_and_renumbers_the_members_pairs() -> None:
    pairs = np.array([[0, 1], [1, 5], [5, 7], [2, 3]])
    assert within(np.array([5, 1, 7]), pairs).tolist() == [[1, 0], [0, 2]]
    assert within(np.array([9]), pairs).shape == (0, 2)
