"""The paper's GPA-ICP, step by step (``--method paper``), for comparison with the publication.

Each patch is down-sampled on a grid of side ``cell`` (paper, III-C) and carries the shape index
of every grid point. Every iteration then runs the six steps of section IV:

1. nearest neighbour of every point in every other cloud that can overlap it (one kd-tree per
   cloud, built once in its own frame; the queries are moved into it; points far from the other
   cloud's outline are skipped and the search reaches 5 cells, which changes no useful MNN);
2. mutual nearest neighbours (MNN);
3. independent sets of MNN, discarding those with two points of one cloud;
4. the mean cloud K (mean of each set) and weights ``1 - MAD(SI)`` per set;
5. a weighted SVD rigid transform per cloud onto its part of K;
6. all transforms applied at once.

It stops when the largest translation of a step falls below ``tol`` (the paper's criterion) or
after ``max_iter`` iterations. Point-to-point on the down-sampled points only, as published. The
gauge is fixed as in the default method so both report in the same frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from merge.core.downsample import grid_downsample
from merge.core.errors import MergeCancelled
from merge.core.kabsch import weighted_rigid_transform
from merge.core.patchset import Patch
from merge.paper.correspondences import (
    IndependentSets,
    independent_sets,
    mutual_nearest_neighbours,
    set_means,
    set_weights,
)
from merge.paper.shape_index import shape_index

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class PaperResult:
    """Transforms ``q = R p + t``, iterations, convergence and the mean residual per iteration."""

    R: FloatArray
    t: FloatArray
    iterations: int
    converged: bool
    history: list[float]


def _inside(points: FloatArray, lo: FloatArray, hi: FloatArray) -> IntArray:
    """Indices of points whose XY lies in the box ``[lo, hi]``."""
    ok = (
        (points[:, 0] >= lo[0])
        & (points[:, 0] <= hi[0])
        & (points[:, 1] >= lo[1])
        & (points[:, 1] <= hi[1])
    )
    out: IntArray = np.flatnonzero(ok)
    return out


def paper_gpa_icp(
    patches: Sequence[Patch],
    pairs: IntArray,
    R0: FloatArray,
    t0: FloatArray,
    *,
    cell: float,
    max_iter: int = 200,
    tol: float | None = None,
    progress: Callable[[int, float], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> PaperResult:
    """Run the published GPA-ICP from the initial transforms ``R0, t0`` (metres).

    Parameters
    ----------
    patches : sequence of Patch
    pairs : (k, 2) int array
        Clouds that can overlap; nearest neighbours are searched only between these.
    R0, t0 : (n, 3, 3), (n, 3) arrays
    cell : float, keyword-only
        Down-sampling cell, metres.
    max_iter : int, keyword-only
    tol : float, keyword-only
        Stop when every cloud's translation in a step is below this (metres); default
        ``cell / 1000``.
    progress, cancel : callables, keyword-only
        Per-iteration report ``(iteration, mean residual in metres)`` and cancellation poll.
    """
    tol = cell / 1000.0 if tol is None else tol
    clouds = _clouds(patches, cell)
    n = len(patches)
    # state: q = R_c p_local + s_c
    R = np.array(R0, dtype=np.float64, copy=True)
    s = np.einsum("cij,cj->ci", R, clouds.centre) + np.asarray(t0, dtype=np.float64)
    history: list[float] = []
    converged = False
    it = 0
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    for it in range(1, max_iter + 1):
        if cancel is not None and cancel():
            raise MergeCancelled("merge cancelled")
        world = np.concatenate([clouds.local[c] @ R[c].T + s[c] for c in range(n)])
        # steps 1 and 2: nearest neighbours both ways, kept when mutual
        edges = _mutual_pairs(clouds, world, pairs, R, s, cell)
        if not edges:
            break
        # step 3: independent sets with one point per cloud
        sets = independent_sets(np.concatenate(edges), clouds.cloud_of)
        if sets.n_sets == 0:
            break
        # step 4: the mean cloud K and the weights 1 - MAD(SI)
        K = set_means(world, sets)
        W = set_weights(clouds.shape_index, sets)
        resid = np.linalg.norm(world[sets.members] - K[sets.set_of], axis=1)
        history.append(float(np.mean(resid)))
        # steps 5 and 6: a weighted rigid transform per cloud onto K, applied to all at once
        largest = _procrustes_step(clouds, sets, K, W, R, s)
        if progress is not None:
            progress(it, history[-1])
        if largest < tol:
            converged = True
            break
    t = s - np.einsum("cij,cj->ci", R, clouds.centre)
    return PaperResult(R=R, t=t, iterations=it, converged=converged, history=history)


@dataclass(frozen=True)
class Clouds:
    """Every patch down-sampled on the grid (paper, III-C), as one point cloud each.

    local : per cloud, its points (m_c, 3) in its own frame, centred on ``centre`` (n, 3).
    trees : per cloud, a kd-tree of ``local`` (built once: queries move into its frame).
    start : (n + 1,) where each cloud's points begin in the clouds end to end.
    cloud_of : the cloud of every point; shape_index : the shape index of every point.
    """

    local: list[FloatArray]
    centre: FloatArray
    trees: list[cKDTree]
    start: IntArray
    cloud_of: IntArray
    shape_index: FloatArray


def _clouds(patches: Sequence[Patch], cell: float) -> Clouds:
    """Each patch on the grid of side ``cell`` (metres), with its shape index."""
    local, si, centre = [], [], []
    for p in patches:
        grid = grid_downsample(p.heights, p.pixel_size, cell=cell, origin=p.origin)
        pts, flat = grid.points()
        c = pts.mean(axis=0)
        local.append(pts - c)  # cloud in its own (centred) frame
        centre.append(c)
        si.append(shape_index(grid.heights, cell).ravel()[flat])
    trees = [cKDTree(pts) for pts in local]
    start = np.concatenate([[0], np.cumsum([len(x) for x in local])]).astype(np.intp)
    cloud_of = np.repeat(np.arange(len(patches)), np.diff(start))
    return Clouds(local, np.array(centre), trees, start, cloud_of, np.concatenate(si))


def _mutual_pairs(
    clouds: Clouds, world: FloatArray, pairs: IntArray, R: FloatArray, s: FloatArray, cell: float
) -> list[IntArray]:
    """Steps 1 and 2: per pair of clouds, its mutual nearest neighbours as rows of point
    indices into ``world`` (the clouds end to end, in the mosaic)."""
    n, start, trees = len(clouds.local), clouds.start, clouds.trees
    margin = 2.0 * cell
    # The paper searches nearest neighbours without a bound; beyond a few cells (after the robust
    # start) a nearest neighbour is never mutual and useful, and the bound makes the search fast.
    reach = 5.0 * cell
    edges = []
    lo = np.array([world[start[c] : start[c + 1], :2].min(axis=0) for c in range(n)])
    hi = np.array([world[start[c] : start[c + 1], :2].max(axis=0) for c in range(n)])
    for a, b in pairs:
        # only points near the other cloud's outline can be mutual nearest neighbours
        wa, wb = world[start[a] : start[a + 1]], world[start[b] : start[b + 1]]
        ia = _inside(wa, lo[b] - margin, hi[b] + margin)
        ib = _inside(wb, lo[a] - margin, hi[a] + margin)
        if len(ia) == 0 or len(ib) == 0:
            continue
        # queries moved into the other cloud's own frame; "no neighbour within reach" comes
        # back as index len(cloud), mapped to -1 below
        _, nn_ab = trees[b].query((wa[ia] - s[b]) @ R[b], distance_upper_bound=reach, workers=-1)
        _, nn_ba = trees[a].query((wb[ib] - s[a]) @ R[a], distance_upper_bound=reach, workers=-1)
        # map to window-local indices so the mutual test compares like with like
        pos_b = np.full(len(wb) + 1, -1, dtype=np.intp)
        pos_b[ib] = np.arange(len(ib))
        pos_a = np.full(len(wa) + 1, -1, dtype=np.intp)
        pos_a[ia] = np.arange(len(ia))
        i, j = mutual_nearest_neighbours(pos_b[nn_ab], pos_a[nn_ba])
        if len(i):
            edges.append(np.column_stack([ia[i] + start[a], ib[j] + start[b]]))
    return edges


def _procrustes_step(
    clouds: Clouds,
    sets: IndependentSets,
    K: FloatArray,
    W: FloatArray,
    R: FloatArray,
    s: FloatArray,
) -> float:
    """Steps 5 and 6: every cloud's weighted rigid transform onto its part of the mean cloud
    ``K``, written into ``R`` and ``s`` at once; the largest translation it made (metres)."""
    n, start, local = len(clouds.local), clouds.start, clouds.local
    largest = 0.0
    by_cloud = np.argsort(clouds.cloud_of[sets.members], kind="stable")
    bounds = np.searchsorted(clouds.cloud_of[sets.members][by_cloud], np.arange(n + 1))
    for c in range(n):
        mine = by_cloud[bounds[c] : bounds[c + 1]]
        w = W[sets.set_of[mine]]
        if np.count_nonzero(w) < 3:
            continue
        src = local[c][sets.members[mine] - start[c]]
        dst = K[sets.set_of[mine]]
        Rc, sc = weighted_rigid_transform(src, dst, w)
        largest = max(largest, float(np.linalg.norm(sc - s[c])))
        R[c], s[c] = Rc, sc
    return largest
