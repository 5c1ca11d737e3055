"""One Gauss-Newton step of the default method: the normal system solved with its priors.

Levenberg damping keeps the places (XY, spin) a patch's own data barely see (XY on a flat
overlap) where they are; directions they see well it leaves free, or it would slow every motion
of many patches together, whose stiffness falls with the square of the mosaic's side. Gaussian
priors on the drift plane, the shift from the start and the spin enter with the data's weight
per unit residual, so the step is that of a proper posterior. One sparse factorisation of the whole
mosaic's system: every patch moves against all others at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix

from merge.core.progress import checkpoint
from merge.core.sparse import solve_symmetric
from merge.refine.normal_system import NormalSystem

FloatArray = NDArray[np.float64]

#: Levenberg damping, relative to the largest curvature of each patch's own unknowns, of the
#: directions whose own curvature is below :data:`WEAK` of that: where it changes a patch's own
#: step by a percent or more. Along the others it acted only on motions of many patches
#: together: a smooth shift of the whole mosaic, held by overlaps whose stiffness over a side of
#: N patches falls as 1 / N², was damped as much as the data held it from 100 x 100 patches on
#: (10,000 patches: the first level's steps fell by 0.6 a step, 17 iterations in all).
DAMPING = 1e-4
WEAK = 1e-2
#: The unknowns the damping holds: XY and spin (a patch's place in the plane). Its height and
#: drift plane are left free: damped too, the drift planes of a large finely sampled mosaic
#: stayed bent along the slow axis, the patch rows' relative tilts, which the scan lines'
#: offsets leave weakly measured, held where the first level put them (2,500 patches of
#: 256 x 256 px: Z 2.98 -> 0.98 nm, map 4.6 -> 1.8 x the floor; the grating sweep and the
#: bench within 1 %; all of it damped by 1e-8 instead took a grating draw's XY 0.5 -> 5.2 nm).
PLACE = np.array([0, 1, 3])
#: Damping of the well-seen directions: only enough to keep the common motions no data see (the
#: gauge, removed after every step) from making the system singular.
FLOOR = 1e-9


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
    # Levenberg damping of the places (PLACE) a patch's own data barely constrain (XY on a flat
    # overlap): they stay put instead of following noise; every direction gets the FLOOR
    top = np.clip(np.linalg.eigvalsh(system.diag)[:, -1:], 0.0, None)
    D = (FLOOR * top + 1e-12)[:, :, None] * np.eye(6)
    mu, V = np.linalg.eigh(system.diag[:, PLACE][:, :, PLACE])
    damp = np.where(mu < WEAK * top, DAMPING - FLOOR, 0.0) * top
    D[:, PLACE[:, None], PLACE[None, :]] += np.einsum("nij,nj,nkj->nik", V, damp, V)
    lam = np.zeros((n, 6))
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
        lam[held] += 1e9 * (float(top.max(initial=0.0)) + 1.0)
    D[:, np.arange(6), np.arange(6)] += lam
    checkpoint()  # a large mosaic's system takes a second to gather (10,000 patches)
    ii, jj = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    base = 6 * np.arange(n)[:, None, None]
    M = coo_matrix(
        (
            np.concatenate([vals, D.ravel()]),
            (
                np.concatenate([rows, (base + ii).ravel()]),
                np.concatenate([cols, (base + jj).ravel()]),
            ),
        ),
        shape=(6 * n, 6 * n),
    )
    checkpoint()
    A = M.tocsc()
    checkpoint()
    out: FloatArray = solve_symmetric(A, g.ravel()).reshape(n, 6)
    return out
