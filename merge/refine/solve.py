"""One Gauss-Newton step of the default method: the normal system solved with its priors.

Levenberg damping relative to each patch's own curvature keeps directions its data do not see
(XY on a flat overlap) where they are; Gaussian priors on the drift plane, the shift from the
start and the spin enter with the data's weight per unit residual, so the step is that of a
proper posterior. One sparse factorisation of the whole mosaic's system: every patch moves
against all others at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve

from merge.refine.normal_system import NormalSystem

FloatArray = NDArray[np.float64]

#: Levenberg damping, relative to the largest curvature of each patch's own unknowns.
DAMPING = 1e-4


@dataclass(frozen=True)
class Priors:
    """Gaussian priors on the absolute state, in the scaled units of the unknowns (pixels)."""

    plane: FloatArray  # (n, 2) drift plane times radius
    plane_sigma: FloatArray  # (2,) along x (the fast axis) and y
    shift: FloatArray  # (n, 2) XY offset from the start
    shift_sigma: float
    spin: FloatArray  # (n,) rotation about z times radius
    spin_sigma: FloatArray  # (n,)


def solve_system(
    system: NormalSystem, priors: Priors, *, held: NDArray[np.bool_] | None = None
) -> FloatArray:
    """Damped solution of the system: ``(n, 6)`` updates (translation, scaled spin and plane).

    A prior ``|value / sigma|²`` enters with the weight the data have per unit residual
    (``1 / residual scale²``), so it is a proper posterior, not a tuning knob. Patches ``held``
    (n,) bool do not move (their updates ~1e-9 of what their data alone would give).
    """
    n = len(system.g)
    rows, cols, vals = system.rows, system.cols, system.vals
    # Levenberg damping relative to each patch's own curvature: directions a patch's data do not
    # constrain (XY on a flat overlap) stay put instead of following noise
    on_diag = rows == cols
    dvals = np.bincount(rows[on_diag], weights=vals[on_diag], minlength=6 * n).reshape(n, 6)
    lam = np.broadcast_to(DAMPING * dvals.max(axis=1, keepdims=True) + 1e-12, (n, 6)).copy()
    g = system.g.copy()
    if system.rscale > 0:
        r2 = system.rscale**2
        for cols_, value, sigma in (
            ([4, 5], priors.plane, np.broadcast_to(priors.plane_sigma, (n, 2))),
            ([0, 1], priors.shift, np.full((n, 1), priors.shift_sigma)),
            ([3], priors.spin[:, None], priors.spin_sigma[:, None]),
        ):
            k = r2 / np.asarray(sigma, dtype=np.float64) ** 2
            lam[:, cols_] += k
            g[:, cols_] -= k * value
    if held is not None:
        lam[held] += 1e9 * (float(dvals.max(initial=0.0)) + 1.0)
    idx = np.arange(6 * n)
    M = coo_matrix(
        (
            np.concatenate([vals, lam.ravel()]),
            (np.concatenate([rows, idx]), np.concatenate([cols, idx])),
        ),
        shape=(6 * n, 6 * n),
    ).tocsc()
    x = spsolve(M, g.ravel())
    out: FloatArray = np.asarray(x, dtype=np.float64).reshape(n, 6)
    return out
