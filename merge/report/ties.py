"""Which patches a chain of overlaps that measured them ties to the mosaic, axis by axis.

A patch's XY standard deviation counts every overlap's information at the placement where the
fit ended. Along an axis no overlap of a block of patches measured, that information is the
faces' roughness at whatever shift the block stands: in overlaps a few pixels wide (15 % of
30 x 60 px chessboard patches, stage errors of 50 nm) a column's pairs held no vertical edge,
the start measured none of them along x, and the refinement kept three columns 120 nm off the
other seven, every patch claiming 2 nm.

So, along x, y and the two diagonals apart, the pairs the start measured well along that axis
tie their patches together (:data:`STRONG`); any other pair ties them when its misfit rises as
one of its patches is moved along the axis
(:func:`merge.report.confirmation.moved_misfit_rise`, only the pairs between two blocks are
tried). Patches outside the largest block of their overlap group (groups that overlap nowhere
are merged each on its own) are not held along that axis: where they lie against the rest is
the stage's placement or a dip of the noise, not a measurement.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.report.confirmation import CONFIRMS, moved_misfit_rise, placement

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: A pair the start measured along an axis to this share of the best any pair was measured
#: (the start's precision cap) ties its patches along it. Less is not enough: a corner's
#: overlap measured along a tilted direction, 92 nm off in x, claimed a fifth of the cap.
STRONG = 0.5
#: The axes, as (name, direction (x, y) in pixels): x, y and the diagonals (a grating at 45°
#: measures one diagonal, and its stripes leave the other to its defects).
AXES = (
    ("x", np.array([1.0, 0.0])),
    ("y", np.array([0.0, 1.0])),
    ("x = y", np.array([1.0, 1.0])),
    ("x = -y", np.array([1.0, -1.0])),
)


def untied(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    pairs: IntArray,
    information: FloatArray,
    *,
    bank: SurfaceBank | None = None,
) -> dict[int, tuple[str, ...]]:
    """The patches no chain of measured overlaps ties to the mosaic's largest block, with the
    axes (:data:`AXES`' names) along which it does not.

    Parameters
    ----------
    patches : sequence of Patch
    transforms : sequence of PatchTransform
        ``T_mosaic_patch`` per patch, where the fit ended.
    pairs : (k, 2) int array
        The pairs the start correlated.
    information : (k, 2, 2) float array
        What the start measured of each (1 / m²; zero: nothing).
    bank : SurfaceBank, keyword-only
        The patches' raw heights as surfaces, if already built.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    n = len(patches)
    out: dict[int, tuple[str, ...]] = {}
    if n < 2 or not len(pairs):
        return out
    group = _blocks(n, pairs)
    largest = np.linalg.eigvalsh(information)[:, 1]
    loose = []  # the axes along which the start's measured pairs leave blocks apart
    for name, u in AXES:
        along = np.einsum("i,kij,j->k", u, information, u) / float(u @ u)
        tied = (along > 0) & (along >= STRONG * largest.max())
        label = _blocks(n, pairs[tied])
        if _outside_largest(label, group).any():
            loose.append((name, u, tied, label))
    if not loose:
        return out
    surfaces, state = placement(patches, transforms, bank)
    for name, u, tied, label in loose:
        step = ((int(u[0]), int(u[1])), (-int(u[0]), -int(u[1])))
        blocks = _Blocks(label)
        # a pair between two blocks that confirms the axis joins them
        for k in np.flatnonzero(~tied).tolist():
            a, b = int(pairs[k, 0]), int(pairs[k, 1])
            if blocks.find(a) == blocks.find(b):
                continue
            checkpoint()
            rise = moved_misfit_rise(
                surfaces, state, pairs[k : k + 1], b, directions=step, enough=CONFIRMS
            )
            if rise >= CONFIRMS:
                blocks.join(a, b)
        joined = np.array([blocks.find(c) for c in range(n)], dtype=np.intp)
        for c in np.flatnonzero(_outside_largest(joined, group)).tolist():
            out[c] = (*out.get(c, ()), name)
    return out


class _Blocks:
    """Patches joined into blocks one pair at a time (a disjoint-set forest)."""

    def __init__(self, label: IntArray) -> None:
        """Start from the blocks ``label`` (n,) names (:func:`_blocks`)."""
        root: dict[int, int] = {}  # each block's first patch is its root
        for c, block in enumerate(label.tolist()):
            root.setdefault(block, c)
        self.parent = [root[block] for block in label.tolist()]

    def find(self, c: int) -> int:
        """The root of ``c``'s block."""
        while self.parent[c] != c:
            self.parent[c] = self.parent[self.parent[c]]
            c = self.parent[c]
        return c

    def join(self, a: int, b: int) -> None:
        """Join the blocks of ``a`` and ``b``."""
        self.parent[self.find(a)] = self.find(b)


def _outside_largest(label: IntArray, group: IntArray) -> NDArray[np.bool_]:
    """(n,) whether each patch lies outside the largest block (``label``) of its overlap
    group (``group``): groups that overlap nowhere are merged each on its own."""
    base = int(label.max()) + 1
    key, count = np.unique(group * base + label, return_counts=True)
    in_group, block = key // base, key % base
    order = np.lexsort((-count, in_group))  # by group, the largest block first
    first = order[np.r_[True, in_group[order][1:] != in_group[order][:-1]]]
    main = np.zeros(int(group.max()) + 1, dtype=np.intp)
    main[in_group[first]] = block[first]
    out: NDArray[np.bool_] = label != main[group]
    return out


def _blocks(n: int, edges: IntArray) -> IntArray:
    """(n,) the connected block of every patch over ``edges`` (m, 2)."""
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return np.asarray(label, dtype=np.intp)
