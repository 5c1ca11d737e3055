"""Sparse symmetric systems of a mosaic: one ordering for all their factorisations.

Every system the merge solves is symmetric (normal equations, their information matrices), with
the structure of the mosaic's grid of patches. SuperLU's default column ordering (COLAMD) knows
nothing of the symmetry; the minimum degree ordering of ``A' + A`` does, and fills far less: a
grid of 100 x 100 patches (60,000 unknowns in 6 x 6 blocks) factorised in 2.4 s instead of 8.2,
with half the nonzeros in its factors (26 M against 50 M).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csc_matrix
from scipy.sparse.linalg import SuperLU, splu, spsolve

FloatArray = NDArray[np.float64]

#: SuperLU's column ordering for symmetric systems.
ORDERING = "MMD_AT_PLUS_A"


def solve_symmetric(A: csc_matrix, b: FloatArray) -> FloatArray:
    """``A x = b`` for a sparse symmetric ``A``; ``b`` (m,) or (m, k)."""
    x: FloatArray = np.asarray(spsolve(A, b, permc_spec=ORDERING), dtype=np.float64)
    return x


def factor_symmetric(A: csc_matrix) -> SuperLU:
    """The LU factors of a sparse symmetric ``A``, for many right-hand sides."""
    return splu(A, permc_spec=ORDERING)
