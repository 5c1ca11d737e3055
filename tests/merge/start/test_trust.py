"""Which pair measurements the coarse start believes: ridges, odd scores, patches in doubt."""

import numpy as np

from merge.start.trust import (
    along_ridge_removed,
    drop_odd_scores,
    drop_unconstrained,
    patches_in_doubt,
    periodic_repeat,
)


def _weights(count: int) -> np.ndarray:
    return np.repeat(np.eye(2)[None], count, axis=0)


def test_a_ridge_takes_away_the_information_along_it() -> None:
    info = np.array([[4.0, 1.0], [1.0, 3.0]])
    np.testing.assert_array_equal(along_ridge_removed(info, ()), info)
    # alike peaks at (dy, dx) = (3, 3) and (-5, -4): a ridge along about x = y
    out = along_ridge_removed(info, [(3, 3), (-5, -4)])
    along = np.array([1.0, 1.0]) / np.sqrt(2.0)
    assert along @ out @ along < 0.02 * np.trace(info)
    across = np.array([1.0, -1.0]) / np.sqrt(2.0)
    assert across @ out @ across > 0.9 * (across @ info @ across)
    # alike peaks all around: a plateau, nothing measured
    np.testing.assert_array_equal(along_ridge_removed(info, [(0, 3), (3, 0)]), np.zeros((2, 2)))


def test_a_direction_the_texture_measures_is_held_whatever_the_edges_measure_across() -> None:
    # patch 0's pairs: four along an edge (y to a tenth of a cell, information 100 per cell²),
    # two of them with the texture beside it measuring x to a cell (information 1)
    across = np.array([[0.0, 0.0], [0.0, 100.0]])
    textured = np.array([[1.0, 0.0], [0.0, 0.0]])
    W = np.array([across + textured, across + textured, across, across])
    pairs = np.array([[0, 1], [0, 2], [0, 3], [0, 4]])
    x = np.zeros((5, 2))
    x[0] = (40.0, 3.0)
    # x holds 2 of the 400 the patch has across: under the aperture, taken for a leak
    out, complete = drop_unconstrained(x, pairs, W)
    np.testing.assert_allclose(out[0], (0.0, 3.0), atol=1e-12)
    assert not complete[0]
    texture = np.array([textured, textured, np.zeros((2, 2)), np.zeros((2, 2))])
    out, complete = drop_unconstrained(x, pairs, W, texture=texture, least=0.5)
    np.testing.assert_allclose(out[0], (40.0, 3.0))
    assert not complete[0]  # to a cell, not to a peak's precision: the refinement frees it
    # the same x information from the edges' angles, no texture: not held
    leak = np.array([[0.5, 0.0], [0.0, 0.0]])
    W = np.array([across + leak] * 4)
    out, complete = drop_unconstrained(x, pairs, W, texture=np.zeros((4, 2, 2)), least=0.5)
    np.testing.assert_allclose(out[0], (0.0, 3.0), atol=1e-12)
    assert not complete[0]


def test_a_peak_far_below_the_usual_score_is_not_a_measurement() -> None:
    # a textured surface: true peaks score 0.95-0.99; one pair found only a chance peak
    score = np.array([0.97, 0.96, 0.98, 0.99, 0.95, 0.97, 0.98, 0.96, 0.97, 0.56, np.nan])
    w = _weights(len(score))
    drop_odd_scores(score, w)
    assert not w[9].any()
    assert all(w[i].any() for i in range(9)) and w[10].any()  # unmatched pairs are left alone


def test_a_low_score_that_stands_out_of_its_window_is_kept() -> None:
    # a grating: pairs holding an edge score 0.95-0.99; one holds only a face's roughness,
    # which scores 0.5 but stands 5.5 spreads above the chance peaks of its own window
    score = np.array([0.97, 0.96, 0.98, 0.99, 0.95, 0.97, 0.98, 0.96, 0.97, 0.50, 0.52])
    excess = np.array([9.0] * 9 + [5.5, 1.0])
    w = _weights(len(score))
    drop_odd_scores(score, w, excess=excess, significance=3.0)
    assert w[9].any()  # a real peak
    assert not w[10].any()  # as likely as chance: dropped
    assert all(w[i].any() for i in range(9))


def test_scores_that_vary_widely_drop_nothing() -> None:
    # a sparse grating: peaks from 0.6 (roughness along an edge) to 0.99 (corners) are all real
    score = np.linspace(0.6, 0.99, 12)
    w = _weights(len(score))
    drop_odd_scores(score, w)
    assert w.any(axis=(1, 2)).all()
    few = _weights(5)
    drop_odd_scores(np.array([0.99, 0.99, 0.99, 0.99, 0.4]), few)
    assert few.any(axis=(1, 2)).all()  # too few pairs to know what is usual


def testpatches_in_doubt_are_those_with_conflicting_or_no_trusted_links_seen_in_2d() -> None:
    # a triangle of patches and a fourth linked to patch 2 only; pair (0, 1) conflicts
    pairs = np.array([[0, 1], [1, 2], [0, 2], [2, 3]])
    unmeasured = np.array([False, False, False, True])
    robust = np.array([0.1, 1.0, 1.0, 1.0])
    can = np.ones(4, dtype=bool)
    both = np.broadcast_to(np.eye(2), (4, 2, 2)).copy()
    both[3] = 0.0  # found nothing
    # patches 0 and 1 conflict (though each has a trusted link); patch 3's only pair found
    # nothing; patch 2 is held by its trusted links
    assert sorted(patches_in_doubt(4, pairs, unmeasured, robust, can, both)) == [0, 1, 3]
    # seen along x only (a grating's pairs): where a peak lies along the stripes is a guess,
    # and a pooled search would pick a bump on the ridge; a patch with nothing measured stays
    along_x = np.broadcast_to(np.diag([1.0, 0.0]), (4, 2, 2)).copy()
    along_x[3] = 0.0
    assert patches_in_doubt(4, pairs, unmeasured, robust, can, along_x) == [3]


def test_a_sample_is_periodic_where_a_third_of_its_pairs_repeat_at_one_distance() -> None:
    info = np.repeat(np.eye(2)[None], 9, axis=0)
    none = np.full(9, np.inf)
    assert np.isnan(periodic_repeat(none, info))
    # three of nine pairs repeat 300-320 nm off: periodic, at their median
    three = none.copy()
    three[[1, 4, 7]] = [300e-9, 310e-9, 320e-9]
    assert periodic_repeat(three, info) == 310e-9
    # as many, scattered over 100-330 nm (bumps along edges): not
    scattered = none.copy()
    scattered[[1, 4, 7]] = [100e-9, 200e-9, 330e-9]
    assert np.isnan(periodic_repeat(scattered, info))
    # two of nine: too few; and pairs not measured do not count
    assert np.isnan(periodic_repeat(np.where(np.arange(9) < 2, 300e-9, np.inf), info))
    # two of a 2 x 2 mosaic's four at one distance (bumps along a chessboard's edges): too few
    # however small the mosaic; three of its six (a grating's stripes): periodic
    four = np.repeat(np.eye(2)[None], 4, axis=0)
    assert np.isnan(periodic_repeat(np.array([136e-9, 194e-9, 136e-9, np.inf]), four))
    six = np.repeat(np.eye(2)[None], 6, axis=0)
    stripes = np.array([313e-9, 322e-9, np.inf, 313e-9, np.inf, np.inf])
    assert periodic_repeat(stripes, six) == 313e-9
    unmeasured = info.copy()
    unmeasured[[1, 4]] = 0.0
    assert np.isnan(periodic_repeat(three, unmeasured))
