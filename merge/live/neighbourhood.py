"""A patch's neighbourhood in the live merge: the stored patches it can overlap, its pairs
renumbered to a local list, which patches its coarse start places and which hold the frame,
and the frame that start is in against the mosaic's."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def nominal_neighbours(boxes: FloatArray, c: int, max_shift: float) -> IntArray:
    """The patches whose nominal ``boxes`` (n, 4: x0, y0, x1, y1, metres) patch ``c``'s can
    overlap when the two lie up to ``max_shift`` (metres, along either axis) off their nominal
    places against each other; ``c`` itself not."""
    grown = boxes[c] + np.array([-max_shift, -max_shift, max_shift, max_shift])
    hit = (
        (boxes[:, 0] < grown[2])
        & (boxes[:, 2] > grown[0])
        & (boxes[:, 1] < grown[3])
        & (boxes[:, 3] > grown[1])
    )
    hit[c] = False
    out: IntArray = np.flatnonzero(hit)
    return out


def to_place(
    complete: NDArray[np.bool_], known: NDArray[np.bool_]
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Which members of a coarse start's neighbourhood it places, and which hold the frame.

    The members are the neighbours, then the new patch (last). ``complete`` (m,): whether this
    start measured each one's XY along both axes; ``known`` (m,): whether an earlier start had
    (the new patch's is ignored). The new patch is placed, and so is every neighbour this start
    measured both ways that no earlier one had (an edge alone holds XY across it only), unless
    that would leave no neighbour measured both ways to hold the frame. Returns ``moving`` and
    the ``reference`` that holds the frame: the neighbours not moving that are known both ways,
    or, where there is none, all those not moving.
    """
    complete, known = np.asarray(complete, dtype=bool), np.asarray(known, dtype=bool).copy()
    if complete.shape != known.shape or complete.ndim != 1 or not len(complete):
        raise ValueError(
            f"complete and known must be two (m,) arrays, got {complete.shape}, {known.shape}"
        )
    known[-1] = False
    if not known.any():  # no neighbour known both ways to hold the frame: all of them hold it
        moving = np.zeros(len(complete), dtype=bool)
        moving[-1] = True
        return moving, ~moving
    # a neighbour known both ways never moves: those hold the frame
    return np.append(~known[:-1] & complete[:-1], True), known


def within(members: IntArray, pairs: IntArray) -> IntArray:
    """The ``pairs`` (k, 2) whose patches are both among ``members``, renumbered to their
    places in it."""
    index = {int(j): k for k, j in enumerate(members)}
    sub = [(index[int(a)], index[int(b)]) for a, b in pairs if a in index and b in index]
    return np.array(sub, dtype=np.intp).reshape(-1, 2)


def frame_offset(
    patches: Sequence[Patch], translation: FloatArray, placed: Sequence[PatchTransform]
) -> FloatArray:
    """How far (x, y, z, metres) the mosaic's frame lies from a coarse start's, as the
    ``patches`` already placed say: the mean, over them, of where their centres now are less
    where the start's ``translation`` (n, 3) put them."""
    offsets = []
    for p, t0, tr in zip(patches, translation, placed, strict=True):
        centre = np.array([*p.center, p.median_height])
        offsets.append(tr.apply(centre[None])[0] - (centre + t0))
    out: FloatArray = np.mean(offsets, axis=0)
    return out
