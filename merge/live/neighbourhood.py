"""A patch's neighbourhood in the live merge: its pairs renumbered to a local list, and the
frame its coarse start is in against the mosaic's."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


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
