"""Which patches can overlap: a neighbour graph from nominal footprints.

A kd-tree over footprint centres finds candidate pairs within reach, so building the graph costs
O(n log n) and its size grows linearly with the number of patches on a grid.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def overlapping_pairs(boxes: FloatArray, *, margin: float = 0.0) -> IntArray:
    """Pairs ``(a, b)``, ``a < b``, whose boxes grown by ``margin`` intersect with positive area.

    Parameters
    ----------
    boxes : (n, 4) array
        ``(xmin, ymin, xmax, ymax)`` per patch, metres.
    margin : float, keyword-only
        Distance added on every side (the largest stage error expected), metres.

    Returns
    -------
    (k, 2) int array, sorted.
    """
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 4:
        raise ValueError(f"boxes must be (n, 4), got {b.shape}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    if len(b) < 2:
        return np.empty((0, 2), dtype=np.intp)
    centres = 0.5 * (b[:, :2] + b[:, 2:])
    half = 0.5 * (b[:, 2:] - b[:, :2])
    reach = 2.0 * float(np.hypot(half[:, 0], half[:, 1]).max()) + 2.0 * margin
    cand = cKDTree(centres).query_pairs(reach * (1.0 + 1e-9), output_type="ndarray")
    if len(cand) == 0:
        return np.empty((0, 2), dtype=np.intp)
    a, c = cand[:, 0], cand[:, 1]
    lo = np.maximum(b[a, :2], b[c, :2]) - margin
    hi = np.minimum(b[a, 2:], b[c, 2:]) + margin
    keep = np.all(hi > lo, axis=1)
    pairs = np.sort(cand[keep], axis=1)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    out: IntArray = pairs[order].astype(np.intp)
    return out
