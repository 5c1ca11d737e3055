"""Correspondences of the paper's GPA-ICP (steps 1 to 4): NN, MNN, independent sets, K, W."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def mutual_nearest_neighbours(nn_ab: IntArray, nn_ba: IntArray) -> tuple[IntArray, IntArray]:
    """Index pairs ``(i, j)`` with ``nn_ab[i] == j`` and ``nn_ba[j] == i``.

    Parameters
    ----------
    nn_ab : (na,) int array
        Nearest neighbour in cloud B of every point of cloud A (-1 for none).
    nn_ba : (nb,) int array
        Nearest neighbour in cloud A of every point of cloud B (-1 for none).
    """
    nn_ab = np.asarray(nn_ab, dtype=np.intp)
    nn_ba = np.asarray(nn_ba, dtype=np.intp)
    i = np.flatnonzero((nn_ab >= 0) & (nn_ab < len(nn_ba)))
    j = nn_ab[i]
    mutual = nn_ba[j] == i
    return i[mutual], j[mutual]


@dataclass(frozen=True)
class IndependentSets:
    """Independent sets of MNN (ISM) that hold at most one point per cloud.

    Attributes
    ----------
    members : (m,) int array
        Global point indices of the members of all kept sets.
    set_of : (m,) int array
        Index of the set (0 .. n_sets-1) each member belongs to.
    n_sets : int
    """

    members: IntArray
    set_of: IntArray
    n_sets: int


def independent_sets(edges: IntArray, cloud_of: IntArray) -> IndependentSets:
    """Group points linked by MNN edges into sets; keep those with one point per cloud.

    Parameters
    ----------
    edges : (k, 2) int array
        MNN pairs as global point indices.
    cloud_of : (n,) int array
        Cloud label of every global point.

    Sets with two or more points of one cloud are discarded (paper, step 3 and Fig. 5).
    """
    edges = np.asarray(edges, dtype=np.intp).reshape(-1, 2)
    cloud_of = np.asarray(cloud_of, dtype=np.intp)
    n = len(cloud_of)
    empty = np.empty(0, dtype=np.intp)
    if len(edges) == 0:
        return IndependentSets(empty, empty, 0)
    if edges.min() < 0 or edges.max() >= n:
        raise ValueError("edge indices out of range of cloud_of")
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    linked = np.unique(edges)
    comp = label[linked]
    # a component is kept when its members' cloud labels are all different
    order = np.lexsort((cloud_of[linked], comp))
    comp_s, cloud_s = comp[order], cloud_of[linked][order]
    dup = (comp_s[1:] == comp_s[:-1]) & (cloud_s[1:] == cloud_s[:-1])
    bad = np.unique(comp_s[1:][dup])
    keep = ~np.isin(comp, bad)
    members = linked[keep]
    kept_comp = comp[keep]
    uniq, set_of = np.unique(kept_comp, return_inverse=True)
    return IndependentSets(members.astype(np.intp), set_of.astype(np.intp), len(uniq))


def group_median(values: FloatArray, groups: IntArray, n_groups: int) -> FloatArray:
    """Median of ``values`` within each group (NaN for empty groups or all-NaN groups)."""
    v = np.asarray(values, dtype=np.float64)
    g = np.asarray(groups, dtype=np.intp)
    ok = np.isfinite(v)
    v, g = v[ok], g[ok]
    out = np.full(n_groups, np.nan)
    if v.size == 0:
        return out
    order = np.lexsort((v, g))
    v, g = v[order], g[order]
    counts = np.bincount(g, minlength=n_groups)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    lo = starts[has] + (counts[has] - 1) // 2
    hi = starts[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out


def set_weights(shape_index: FloatArray, sets: IndependentSets) -> FloatArray:
    """Weight ``1 - MAD(SI)`` of every set (paper, eq. 1), clipped to [0, 1].

    ``shape_index`` holds the SI of every global point; NaN members are ignored and a set with
    no defined SI gets weight 1.
    """
    si = np.asarray(shape_index, dtype=np.float64)[sets.members]
    med = group_median(si, sets.set_of, sets.n_sets)
    dev = np.abs(si - med[sets.set_of])
    mad = group_median(dev, sets.set_of, sets.n_sets)
    w = 1.0 - np.nan_to_num(mad, nan=0.0)
    out: FloatArray = np.clip(w, 0.0, 1.0)
    return out


def set_means(points: FloatArray, sets: IndependentSets) -> FloatArray:
    """Mean position of every set: the points of the mean cloud K, shape ``(n_sets, 3)``."""
    p = np.asarray(points, dtype=np.float64)[sets.members]
    counts = np.bincount(sets.set_of, minlength=sets.n_sets).astype(np.float64)
    out = np.empty((sets.n_sets, p.shape[1]))
    for k in range(p.shape[1]):
        out[:, k] = np.bincount(sets.set_of, weights=p[:, k], minlength=sets.n_sets) / counts
    return out
