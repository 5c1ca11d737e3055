"""When a refinement level has converged: how far its steps move the heights.

A step of the patches' unknowns (pixel units: translation, spin and drift plane times each
patch's radius) changes heights directly through Z and the plane, and through the surfaces'
slopes for XY and spin; :func:`height_effect` bounds that change over all patches, and
:func:`remaining` extrapolates what the steps still to come will add, from the ratio of the last
two (Gauss-Newton converges linearly near its solution). :mod:`merge.refine.icp` stops its raw
level once that is a small fraction of the noise.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from merge.core.progress import checkpoint
from merge.refine.bank import SurfaceBank

FloatArray = NDArray[np.float64]

#: Every how many rows of nodes :func:`slope_rms` takes (an RMS over millions of nodes needs no
#: more: a third of a second of 400 patches' refinement went into all of them).
SLOPE_SAMPLE = 7


def slope_rms(bank: SurfaceBank) -> float:
    """RMS of the surfaces' slopes (central differences a pixel either side, as the look-ups
    take them) over every :data:`SLOPE_SAMPLE`-th row of nodes (dimensionless: the slope's
    length, both axes summed, per node)."""
    total, count, m = 0.0, 0, bank.nodes
    for c in range(len(bank.centre)):
        checkpoint()
        grid = bank.grid(c).astype(np.float64)
        rows = np.arange(m, len(grid) - m, SLOPE_SAMPLE)
        gx = (grid[rows, 2 * m :] - grid[rows, : -2 * m]) / (2.0 * bank.dx[c])
        gy = (grid[rows + m, m:-m] - grid[rows - m, m:-m]) / (2.0 * bank.dy[c])
        g2 = gx**2 + gy**2
        valid = np.isfinite(g2)
        total += float(g2[valid].sum())
        count += int(valid.sum())
    return float(np.sqrt(total / count)) if count else 0.0


def height_effect(delta: FloatArray, slope: float) -> float:
    """The largest height change (pixel units) a step ``delta`` (n, 6) makes anywhere, on
    surfaces of RMS ``slope``: its Z and drift plane directly, its XY and spin through the
    slopes."""
    if not np.isfinite(slope) or len(delta) == 0:
        return np.inf
    xy = np.hypot(delta[:, 0], delta[:, 1]) + np.abs(delta[:, 3])
    z = np.abs(delta[:, 2]) + np.hypot(delta[:, 4], delta[:, 5])
    return float((z + slope * xy).max())


def remaining(effect: float, last: float, *, at_least: float = 0.0) -> float:
    """How far the steps still to come will move (same units as ``effect``, the last step's
    effect; ``last`` the one before), their ratio taken as ``at_least`` if it is smaller.

    Gauss-Newton near its solution converges linearly: every step the previous one times about
    the same ratio, so what remains is the last step times ``ratio / (1 - ratio)``, counted as
    no more than the last step itself: with a ratio over a half (or none yet), the tail is
    slow to trust and the last step alone decides, as it did before this rule.
    """
    if not (np.isfinite(last) and last > 0):
        return effect
    ratio = max(effect / last, at_least)
    return effect * min(1.0, ratio / (1.0 - ratio)) if ratio < 1.0 else effect
