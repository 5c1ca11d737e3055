"""Sparse symmetric solves: the same answers as a dense solve, in the fill-reducing ordering."""

from __future__ import annotations

import numpy as np
from scipy.sparse import csc_matrix, random

from merge.core.sparse import factor_symmetric, solve_symmetric


def test_symmetric_solves_equal_the_dense_ones() -> None:
    rng = np.random.default_rng(1)
    R = random(300, 300, density=0.01, random_state=2, format="csc")
    A = csc_matrix(R @ R.T + 0.5 * np.eye(300))
    b = rng.normal(size=(300, 4))
    dense = np.linalg.solve(A.toarray(), b)
    np.testing.assert_allclose(solve_symmetric(A, b[:, 0]), dense[:, 0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(factor_symmetric(A).solve(b), dense, rtol=1e-9, atol=1e-12)
