"""The neighbour graph: the sweep finds exactly the pairs a test of every pair finds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.core import overlap as overlap_module
from merge.core.overlap import moved_boxes, overlap_groups, overlapping_pairs, span_in_patches
from merge.core.transforms import PatchTransform


def _every_pair(boxes: np.ndarray, margin: float) -> list[list[int]]:
    out = []
    for a in range(len(boxes)):
        for c in range(a + 1, len(boxes)):
            lo = np.maximum(boxes[a, :2], boxes[c, :2]) - margin
            hi = np.minimum(boxes[a, 2:], boxes[c, 2:]) + margin
            if np.all(hi > lo):
                out.append([a, c])
    return out


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 40),
    st.sampled_from(["scatter", "column", "row", "grid"]),
    st.floats(0.0, 0.5),
)
def test_the_sweep_finds_every_overlapping_pair_once(
    seed: int, n: int, layout: str, margin: float
) -> None:
    rng = np.random.default_rng(seed)
    size = rng.uniform(0.2, 1.5, (n, 2))
    if layout == "scatter":
        lo = rng.uniform(0.0, 6.0, (n, 2))
    elif layout == "column":  # one x for all: the sweep must run along y
        lo = np.column_stack([np.zeros(n), np.arange(n) * 0.7])
    elif layout == "row":
        lo = np.column_stack([np.arange(n) * 0.7, np.zeros(n)])
    else:
        side = int(np.ceil(np.sqrt(n)))
        lo = np.column_stack([np.arange(n) % side, np.arange(n) // side]) * 0.8
    boxes = np.column_stack([lo, lo + size])
    assert overlapping_pairs(boxes, margin=margin).tolist() == _every_pair(boxes, margin)


def test_groups_are_what_the_pairs_tie_together_through_others() -> None:
    # 0-1-2 a chain, 3-4 a pair, 5 alone
    label = overlap_groups(np.array([[0, 1], [1, 2], [3, 4]]), 6)
    assert label[0] == label[1] == label[2]
    assert label[3] == label[4] != label[0]
    assert len(set(label.tolist())) == 3 and label[5] not in label[:5]
    assert overlap_groups(np.empty((0, 2), dtype=np.intp), 3).tolist() == [0, 1, 2]


def test_chunks_of_candidates_find_the_same_pairs(monkeypatch: pytest.MonkeyPatch) -> None:
    # a large mosaic's candidates come a chunk of patches at a time (a cancel is heard between)
    rng = np.random.default_rng(7)
    lo = rng.uniform(0.0, 6.0, (30, 2))
    boxes = np.column_stack([lo, lo + rng.uniform(0.2, 1.5, (30, 2))])
    whole = overlapping_pairs(boxes, margin=0.1)
    monkeypatch.setattr(overlap_module, "CHUNK", 4)
    assert overlapping_pairs(boxes, margin=0.1).tolist() == whole.tolist()
    assert whole.tolist() == _every_pair(boxes, 0.1)


def test_a_box_moves_where_its_transform_takes_its_corners_not_by_the_translation() -> None:
    """Two patches one above the other, 12 µm from the origin, spun 10 mrad either way: each
    spin turns its patch about the origin by 0.12 µm, which the translation takes back only
    there. Boxes shifted by the translation alone lost the pair (0.23 µm of overlap)."""
    boxes = np.array([[12.0, 1.5, 13.0, 2.5], [12.0, 2.25, 13.0, 3.25]]) * 1e-6
    transforms = []
    for box, spin in zip(boxes, (0.01, -0.01), strict=True):
        centre = 0.5 * (box[:2] + box[2:])
        c, s = np.cos(spin), np.sin(spin)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        t = np.append(centre - R[:2, :2] @ centre, 0.0)  # a spin about the patch's centre
        transforms.append(PatchTransform(R, t))
    moved = moved_boxes(boxes, transforms)
    # about its own centre, a box only grows by its half sides times the spin
    np.testing.assert_allclose(
        0.5 * (moved[:, :2] + moved[:, 2:]), 0.5 * (boxes[:, :2] + boxes[:, 2:]), atol=1e-15
    )
    assert np.all(moved[:, 2:] - moved[:, :2] > boxes[:, 2:] - boxes[:, :2])
    assert overlapping_pairs(moved).tolist() == [[0, 1]]
    shifted = boxes + np.array([tr.t[:2] for tr in transforms]).repeat(2, axis=0).reshape(2, 4)
    assert overlapping_pairs(shifted).tolist() == []  # the old rule lost it


@pytest.mark.parametrize(
    ("rows", "cols", "overlap", "span"), [(4, 10, 0.25, 7.75), (12, 3, 0.5, 6.5)]
)
def test_a_grid_spans_its_pitches_along_its_longer_side(
    rows: int, cols: int, overlap: float, span: float
) -> None:
    pitch = 1.0 - overlap
    lo = np.array([[c * pitch, r * pitch] for r in range(rows) for c in range(cols)])
    boxes = np.column_stack([lo, lo + 1.0]) * 2e-6  # any unit: the span is in patches
    assert span_in_patches(boxes) == pytest.approx(span)


def test_no_patches_span_nothing_and_a_flat_footprint_is_refused() -> None:
    assert span_in_patches(np.zeros((0, 4))) == 0.0
    with pytest.raises(ValueError, match="positive width"):
        span_in_patches(np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 2.0, 0.0]]))
