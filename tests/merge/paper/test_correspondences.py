import numpy as np
import pytest

from merge.paper.correspondences import (
    group_median,
    independent_sets,
    mutual_nearest_neighbours,
    set_means,
    set_weights,
)


def test_mutual_nearest_neighbours_keeps_only_mutual_pairs() -> None:
    nn_ab = np.array([0, 0, 2, -1])  # A1 -> B0 is not mutual (B0 -> A0)
    nn_ba = np.array([0, 3, 2])
    i, j = mutual_nearest_neighbours(nn_ab, nn_ba)
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 0), (2, 2)]


def test_sets_with_two_points_of_one_cloud_are_discarded() -> None:
    # clouds: points 0,1 in cloud 0; 2,3 in cloud 1; 4,5 in cloud 2
    cloud_of = np.array([0, 0, 1, 1, 2, 2])
    edges = np.array(
        [
            [0, 2],
            [2, 4],  # {0, 2, 4}: one point per cloud -> kept
            [1, 3],
            [3, 5],
            [5, 0],
        ]
    )  # the edge 5-0 joins both sets into one
    sets = independent_sets(edges, cloud_of)
    assert sets.n_sets == 0  # {0..5} holds two points of every cloud
    edges = np.array([[0, 2], [2, 4], [1, 3], [3, 5]])
    sets = independent_sets(edges, cloud_of)
    assert sets.n_sets == 2
    groups = sorted(sorted(sets.members[sets.set_of == k].tolist()) for k in range(2))
    assert groups == [[0, 2, 4], [1, 3, 5]]
    edges = np.array([[0, 2], [2, 1]])  # 0 and 1 are both in cloud 0
    assert independent_sets(edges, cloud_of).n_sets == 0


def test_means_and_weights_follow_eq_1() -> None:
    cloud_of = np.array([0, 1, 2, 0, 1])
    sets = independent_sets(np.array([[0, 1], [1, 2], [3, 4]]), cloud_of)
    pts = np.arange(15, dtype=float).reshape(5, 3)
    K = set_means(pts, sets)
    order = np.argsort([sets.members[sets.set_of == k].min() for k in range(sets.n_sets)])
    np.testing.assert_allclose(K[order[0]], pts[[0, 1, 2]].mean(axis=0))
    si = np.array([1.0, 1.0, -1.0, 0.2, 0.2])
    w = set_weights(si, sets)
    # set {0,1,2}: SI 1, 1, -1 -> median 1, deviations 0, 0, 2 -> MAD 0 -> weight 1
    # set {3,4}: identical shapes -> weight 1
    assert w.tolist() == pytest.approx([1.0, 1.0])
    si = np.array([1.0, -1.0, 0.0, 0.5, -0.5])
    w = set_weights(si, sets)
    assert w[order[0]] == pytest.approx(0.0)  # median 0, deviations 1, 1, 0 -> MAD 1
    assert w[order[1]] == pytest.approx(0.5)


def test_group_median() -> None:
    v = np.array([3.0, 1.0, 2.0, 10.0, 20.0, np.nan])
    g = np.array([0, 0, 0, 1, 1, 2])
    assert group_median(v, g, 3)[:2].tolist() == [2.0, 15.0]
    assert np.isnan(group_median(v, g, 3)[2])
