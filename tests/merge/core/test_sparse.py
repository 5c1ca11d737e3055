"""Sparse symmetric solves: the same answers as a dense solve, in the fill-reducing ordering."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import pytest
from scipy.sparse import csc_matrix, diags, eye, kron, random

from merge.core.errors import MergeCancelled
from merge.core.progress import tracking
from merge.core.sparse import (
    LISTEN_FROM,
    _listening,
    factor_symmetric,
    grouped_order,
    listened,
    solve_symmetric,
    sum_at,
)


def test_symmetric_solves_equal_the_dense_ones() -> None:
    rng = np.random.default_rng(1)
    R = random(300, 300, density=0.01, random_state=2, format="csc")
    A = csc_matrix(R @ R.T + 0.5 * np.eye(300))
    b = rng.normal(size=(300, 4))
    dense = np.linalg.solve(A.toarray(), b)
    np.testing.assert_allclose(solve_symmetric(A, b[:, 0]), dense[:, 0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(factor_symmetric(A).solve(b), dense, rtol=1e-9, atol=1e-12)


def _slow_work(release: threading.Event, began: threading.Event) -> Callable[[], int]:
    def work() -> int:
        began.set()
        release.wait(10)  # a factorisation that takes as long as the test wants
        return 7

    return work


def test_a_cancel_stops_a_large_factorisation_at_once() -> None:
    release, began = threading.Event(), threading.Event()
    cancel = threading.Event()
    threading.Timer(0.2, cancel.set).start()
    with tracking(None, cancel.is_set), pytest.raises(MergeCancelled):
        _listening(_slow_work(release, began), LISTEN_FROM)
    assert began.is_set() and not release.is_set()  # heard while the work still ran
    release.set()


def test_a_helper_thread_hands_back_its_result_and_its_error() -> None:
    release, began = threading.Event(), threading.Event()
    release.set()
    assert _listening(_slow_work(release, began), LISTEN_FROM) == 7

    def failing() -> int:
        raise RuntimeError("singular")

    with pytest.raises(RuntimeError, match="singular"):
        _listening(failing, LISTEN_FROM)


def test_large_symmetric_solves_on_the_helper_equal_the_small_path() -> None:
    n = 110  # a grid of n x n unknowns, past LISTEN_FROM
    line = diags([-np.ones(n - 1), 4.1 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    A = csc_matrix(kron(eye(n), line) - kron(diags([np.ones(n - 1)] * 2, [-1, 1]), eye(n)))
    assert A.shape[0] >= LISTEN_FROM
    b = np.random.default_rng(3).normal(size=A.shape[0])
    x = solve_symmetric(A, b)
    np.testing.assert_allclose(A @ x, b, atol=1e-9)
    np.testing.assert_allclose(factor_symmetric(A).solve(b), x, atol=1e-9)


def test_positive_definite_systems_keep_their_symmetric_order() -> None:
    # pairs of unknowns whose link outweighs one of their diagonals, yet positive definite (a
    # weak unit beside a strong one): partial pivoting swaps rows out of the fill-reducing
    # order there (scipy's default did, here); a positive definite system needs no pivot but
    # its diagonal
    n = 100
    block = np.array([[1.0, 2.0], [2.0, 5.0]])
    chain = diags([0.1 * np.ones(2 * n - 1), np.zeros(2 * n), 0.1 * np.ones(2 * n - 1)], [-1, 0, 1])
    A = csc_matrix(kron(eye(n), block) + chain)
    assert np.linalg.eigvalsh(A.toarray()).min() > 0
    factor = factor_symmetric(A)
    np.testing.assert_array_equal(factor.perm_r, factor.perm_c)
    b = np.random.default_rng(4).normal(size=2 * n)
    np.testing.assert_allclose(solve_symmetric(A, b), np.linalg.solve(A.toarray(), b), rtol=1e-9)


def test_sums_at_equal_numpy_add_at() -> None:
    rng = np.random.default_rng(3)
    index = rng.integers(0, 7, 50)
    values = rng.normal(size=(50, 6, 6))
    expected = np.zeros((9, 6, 6))
    np.add.at(expected, index, values)
    out = sum_at(index, values, 9)
    assert out.shape == (9, 6, 6)
    np.testing.assert_allclose(out, expected, rtol=1e-14, atol=1e-14)
    assert not out[7:].any()  # indices never taken stay zero
    assert sum_at(np.empty(0, dtype=np.intp), np.empty((0, 6)), 3).shape == (3, 6)
    with pytest.raises(ValueError, match="one per value"):
        sum_at(index[:-1], values, 9)


def _grid(n: int) -> csc_matrix:
    """A grid of n x n unknowns, each tied to its four neighbours (positive definite)."""
    line = diags([-np.ones(n - 1), 4.1 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    return csc_matrix(kron(eye(n), line) - kron(diags([np.ones(n - 1)] * 2, [-1, 1]), eye(n)))


def test_grouped_orders_keep_each_group_together_and_solve_alike() -> None:
    A = _grid(30)
    groups = np.arange(A.shape[0]) // 3  # three neighbours along a grid line
    order = grouped_order(A, groups)
    assert sorted(order.tolist()) == list(range(A.shape[0]))
    # a group's unknowns follow one another, in their own order
    in_order = groups[order]
    starts = np.flatnonzero(np.r_[True, in_order[1:] != in_order[:-1]])
    assert len(starts) == groups.max() + 1
    assert np.all(np.diff(order)[in_order[1:] == in_order[:-1]] == 1)
    b = np.random.default_rng(5).normal(size=A.shape[0])
    np.testing.assert_allclose(solve_symmetric(A, b, groups=groups), solve_symmetric(A, b))


def test_grouped_orders_refuse_labels_that_are_not_one_per_unknown() -> None:
    A = _grid(4)
    with pytest.raises(ValueError, match="16 labels"):
        grouped_order(A, np.zeros(15, dtype=np.intp))
    with pytest.raises(ValueError, match="16 labels"):
        grouped_order(A, -np.ones(16, dtype=np.intp))


def test_listened_work_is_cancelled_at_once() -> None:
    release, began = threading.Event(), threading.Event()
    cancel = threading.Event()
    threading.Timer(0.2, cancel.set).start()
    with tracking(None, cancel.is_set), pytest.raises(MergeCancelled):
        listened(_slow_work(release, began))
    assert began.is_set() and not release.is_set()
    release.set()
