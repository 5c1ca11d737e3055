import numpy as np

from merge.start.network import solve_pair_differences


def test_recovers_offsets_and_rejects_an_outlier() -> None:
    rng = np.random.default_rng(0)
    n = 12
    x = rng.normal(size=(n, 2))
    x -= x.mean(axis=0)
    pairs = np.array([(a, b) for a in range(n) for b in range(a + 1, min(a + 4, n))])
    m = x[pairs[:, 0]] - x[pairs[:, 1]] + rng.normal(0, 1e-3, (len(pairs), 2))
    m[5] += [5.0, -3.0]  # one wrong measurement
    sol = solve_pair_differences(n, pairs, m, np.full(len(pairs), 1e6))
    np.testing.assert_allclose(sol.x, x, atol=5e-3)
    assert sol.robust[5] < 0.01


def test_matrix_weights_use_only_the_informative_direction() -> None:
    # a pair that knows x only must not drag y
    pairs = np.array([[0, 1], [1, 2], [0, 2]])
    m = np.array([[1.0, 100.0], [1.0, 0.0], [2.0, 0.0]])
    W = np.array([np.diag([1.0, 0.0]), np.eye(2), np.eye(2)])
    sol = solve_pair_differences(3, pairs, m, W, robust_iterations=0)
    d = sol.x[0] - sol.x[1]
    assert abs(d[0] - 1.0) < 1e-6 and abs(d[1]) < 1e-6


def test_each_group_keeps_zero_mean_and_isolated_patches_stay() -> None:
    pairs = np.array([[0, 1], [2, 3]])
    m = np.array([2.0, -4.0])
    sol = solve_pair_differences(5, pairs, m, np.array([1.0, 1.0]), robust_iterations=0)
    x = sol.x[:, 0]
    np.testing.assert_allclose(x[:4], [1, -1, -2, 2], atol=1e-6)
    assert abs(x[4]) < 1e-9
    assert sol.component[0] == sol.component[1] != sol.component[2]
