"""Diagonal blocks of a sparse inverse, slab by slab, against the dense inverse."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import csr_matrix

from merge.core.selected_inverse import diagonal_blocks, slabs


def _grid_pairs(rows: int, cols: int) -> np.ndarray:
    """Units of a rows x cols grid linked to their eight neighbours."""
    out = []
    for i in range(rows):
        for j in range(cols):
            for di, dj in ((0, 1), (1, -1), (1, 0), (1, 1)):
                a, b = i + di, j + dj
                if 0 <= a < rows and 0 <= b < cols:
                    out.append((i * cols + j, a * cols + b))
    return np.array(out, dtype=np.intp).reshape(-1, 2)


def _spd(pairs: np.ndarray, n: int, size: int, seed: int) -> np.ndarray:
    """A random symmetric positive definite matrix with a size x size block per unit and per
    linked pair, nothing elsewhere."""
    rng = np.random.default_rng(seed)
    M = np.zeros((n * size, n * size))
    for a, b in pairs:
        J = rng.normal(size=(2 * size, 2 * size))
        idx = np.r_[a * size : (a + 1) * size, b * size : (b + 1) * size]
        M[np.ix_(idx, idx)] += J @ J.T
    return M + 0.1 * np.eye(n * size)


def _dense_blocks(M: np.ndarray, size: int) -> np.ndarray:
    inv = np.linalg.inv(M)
    n = M.shape[0] // size
    return np.array([inv[u * size : (u + 1) * size, u * size : (u + 1) * size] for u in range(n)])


def test_every_link_joins_a_slab_to_itself_or_the_next() -> None:
    pairs = _grid_pairs(6, 9)
    parts = slabs(pairs, 54)
    slab_of = np.empty(54, dtype=int)
    for k, p in enumerate(parts):
        slab_of[p] = k
    assert sorted(np.concatenate(parts).tolist()) == list(range(54))
    assert (np.abs(slab_of[pairs[:, 0]] - slab_of[pairs[:, 1]]) <= 1).all()


def test_a_row_by_row_order_cuts_a_grid_into_rows() -> None:
    pairs = _grid_pairs(5, 8)
    parts = slabs(pairs, 40, np.arange(40))
    # a unit links to the row below and one unit further: slabs of a row and a unit or so
    assert max(len(p) for p in parts) <= 9
    assert len(parts) >= 4


def test_an_order_must_hold_every_unit_once() -> None:
    with pytest.raises(ValueError, match="every unit"):
        slabs(_grid_pairs(2, 2), 4, np.array([0, 1, 1, 3]))


def test_the_blocks_equal_those_of_the_dense_inverse() -> None:
    pairs = _grid_pairs(4, 5)
    M = _spd(pairs, 20, 6, seed=1)
    got = diagonal_blocks(csr_matrix(M), 6, pairs=pairs)
    np.testing.assert_allclose(got, _dense_blocks(M, 6), rtol=1e-9, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(
    rows=st.integers(1, 4),
    cols=st.integers(1, 5),
    size=st.integers(1, 3),
    seed=st.integers(0, 1000),
    ordered=st.booleans(),
)
def test_any_grid_any_order(rows: int, cols: int, size: int, seed: int, ordered: bool) -> None:
    n = rows * cols
    pairs = _grid_pairs(rows, cols)
    M = _spd(pairs, n, size, seed)
    order = np.random.default_rng(seed).permutation(n) if ordered else None
    got = diagonal_blocks(csr_matrix(M), size, slabs(pairs, n, order))
    np.testing.assert_allclose(got, _dense_blocks(M, size), rtol=1e-8, atol=1e-12)


def test_a_matrix_not_in_whole_units_is_refused() -> None:
    with pytest.raises(ValueError, match="whole units"):
        diagonal_blocks(csr_matrix(np.eye(7)), 6)
