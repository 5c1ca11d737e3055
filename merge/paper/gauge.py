"""The gauge of a simultaneous merge: the mosaic as a whole stays where the stage put it.

Moving every patch by one common rigid motion changes no overlap residual, so the solution is
only defined up to that motion. We pick it in two parts:

* rotation: the patches' rotations average to identity. Each patch's scan frame is off by a small
  random rotation; their mean is the best estimate of "no rotation". (Fitting the rotation to the
  nominal placement instead would inherit the tilt of the Z staircase: drift that accumulates row
  after row looks like a sample tilt, and a merged mosaic would come out tilted.)
* translation: all patch points move, on average, by zero from their nominal places: the stage's
  mean position and the raw mean height are kept.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.transforms import orthonormalize

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def nominal_points(patches: Sequence[Patch], *, stride: int = 4) -> tuple[FloatArray, IntArray]:
    """Every ``stride``-th valid point of every patch at its nominal place ``(m, 3)``, and owner."""
    pts, owner = [], []
    for c, p in enumerate(patches):
        xx, yy = p.pixel_coordinates()
        sl = (slice(None, None, stride), slice(None, None, stride))
        q = np.column_stack([xx[sl].ravel(), yy[sl].ravel(), p.heights[sl].ravel()])
        q = q[np.isfinite(q[:, 2])]
        pts.append(q)
        owner.append(np.full(len(q), c, dtype=np.intp))
    return np.concatenate(pts), np.concatenate(owner)


def anchor_to_nominal(
    nominal: FloatArray, owner: IntArray, R: FloatArray, t: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Compose every ``q = R p + t`` with the gauge motion ``G`` (module notes); returns ``G ∘ T``.

    Parameters
    ----------
    nominal : (m, 3) array
        Sample points of all patches at their nominal places (:func:`nominal_points`).
    owner : (m,) int array
        Patch of every point.
    R, t : (n, 3, 3), (n, 3) arrays
    """
    G = orthonormalize(R.mean(axis=0)).T
    R_new = np.einsum("ij,cjk->cik", G, R)
    t_rot = t @ G.T
    current = np.einsum("mij,mj->mi", R_new[owner], nominal) + t_rot[owner]
    return R_new, t_rot + (nominal - current).mean(axis=0)
