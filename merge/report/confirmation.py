"""Whether a patch's texture confirms where the refinement put it: the misfit rises when the patch
is moved off its place.

The XY standard deviations of :mod:`merge.report.uncertainty` are the curvature of the misfit
where the fit ended. That is the truth when the fit ended at the true registration; it is not
when the refinement alone placed a patch the start could not measure (:mod:`merge.start`) and
its texture is weaker than the noise: rough but flat overlaps of small patches hold slopes
everywhere, so the misfit curves as sharply at a dip of the noise as at the registration. Of a
variation of the bench (flat roughness of 1.5 nm under 1.9 nm of noise, 22 x 45 px patches),
two patches so placed lay 120 and 185 nm off their neighbours' registration, each claiming 6 nm.

What tells the two apart is the misfit a few texture lengths away. Registered, the patch's
points lie closer to its neighbours' surfaces than anywhere near (the texture's variance
decorrelates as it moves off); at a dip of the noise the misfit around is as low, on average.
So the patch is moved by 2, 4 and 8 of its pixels along ±x and ±y, its neighbours held, each
overlap's Z offset fitted again, and the rise of its squared residuals over the same points is
counted in standard errors (:func:`moved_misfit_rise`): the least over the four directions, the
most over the distances (the texture's length is not known).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.rows import feet, heights_above
from merge.refine.runs import RowBlock
from merge.refine.state import MosaicState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Distances a patch is moved, in its own pixels.
STEPS = (2, 4, 8)
#: Rise of the misfit, in standard errors, from which a patch's texture confirms its place.
#: Measured on the variations' draws (``benchmarks/merge_variations.py``): the two patches
#: placed on noise rose by 0.2 and 0.9; patches the start had measured, at 0.5-2 nm of noise on
#: every surface, by 4.8 at least (a chessboard's face), 6-30 mostly.
CONFIRMS = 3.0
#: Fewest points of the patch over its neighbours for a move to count.
MIN_POINTS = 50
#: The directions a patch is moved in (x, y).
COMPASS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def moved_misfit_rise(
    bank: SurfaceBank,
    state: MosaicState,
    pairs: IntArray,
    c: int,
    *,
    directions: Sequence[tuple[int, int]] = COMPASS,
    enough: float = np.inf,
) -> float:
    """How many standard errors patch ``c``'s misfit over its neighbours rises when it is moved.

    Parameters
    ----------
    bank : SurfaceBank
        The patches' surfaces (pixel units of the bank's scale).
    state : MosaicState
        Where every patch lies (the fit's end).
    pairs : (k, 2) int array
        Pairs that overlap there; those with ``c`` count.
    c : int
        The patch.
    directions : sequence of (x, y), keyword-only
        The directions it is moved in (default ±x and ±y).
    enough : float, keyword-only
        A rise that answers the caller's question: the distances after the first to reach it
        are not tried (the rise returned is then at least ``enough``, not the largest).

    Returns
    -------
    float
        Over :data:`STEPS`, the largest of the least rise over the ``directions``: the
        sum, over ``c``'s points on its neighbours' surfaces that stay on them, of the moved
        squared residual less the fitted one (each overlap's Z offset fitted again), over its
        standard error. NaN where no move keeps :data:`MIN_POINTS` points.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    mine = pairs[(pairs == c).any(axis=1)]
    if not len(mine):
        return float("nan")
    pitch = np.array([bank.dx[c], bank.dy[c]], dtype=np.float64)
    margin = 1.5 * float(max(bank.dx.max(), bank.dy.max())) + max(STEPS) * float(pitch.max())
    runs = bank.candidates(mine, state.R, state.s, margin)
    # c's points over its neighbours (a source's runs follow each other)
    own = np.flatnonzero(runs.src == c)
    if not len(own):
        return float("nan")
    rows = bank.rows(runs, int(own[0]), int(own[-1]) + 1)
    checkpoint()
    r0, valid0 = _moved_residuals(bank, rows, state, np.zeros((1, 3)))
    best = float("nan")
    for step in STEPS:
        checkpoint()
        shifts = np.array([[step * pitch[0] * x, step * pitch[1] * y, 0.0] for x, y in directions])
        r1, valid1 = _moved_residuals(bank, rows, state, shifts)
        rises = []
        for k in range(len(directions)):
            ok = valid0[0] & valid1[k]
            if ok.sum() < MIN_POINTS:
                continue
            rises.append(_rise(r0[0, ok], r1[k, ok], rows.dst[ok]))
        if len(rises) == len(directions) and not min(rises) <= best:  # NaN-safe max
            best = min(rises)
        if best >= enough:
            break
    return best


def _moved_residuals(
    bank: SurfaceBank, rows: RowBlock, state: MosaicState, shifts: FloatArray
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The residuals (K, m) of ``rows``, all of one source patch, and their validity, with
    that patch moved by each of ``shifts`` (K, 3; mosaic frame, the bank's units): as
    :func:`merge.refine.rows.residuals` of the moved placement, every move in one look-up
    (moving the source by ``d`` moves every foot by ``R_dst' d``)."""
    _, p_dst, solid = feet(bank, rows, state)
    moved = p_dst[None] + np.einsum("mji,kj->kmi", state.R[rows.dst], shifts)
    k, m = moved.shape[:2]
    tile = np.tile(np.arange(m), k)
    r, ok, _, _ = heights_above(
        bank, rows.dst[tile], moved.reshape(-1, 3), state.slope[rows.dst][tile], solid[tile]
    )
    return r.reshape(k, m), ok.reshape(k, m)


def _rise(fitted: FloatArray, moved: FloatArray, dst: IntArray) -> float:
    """The rise of the squared residuals from ``fitted`` to ``moved`` (each with its mean per
    destination ``dst`` taken out) in standard errors of their sum."""
    fitted, moved = fitted.copy(), moved.copy()
    for j in np.unique(dst).tolist():
        here = dst == j
        fitted[here] -= fitted[here].mean()
        moved[here] -= moved[here].mean()
    rise = moved**2 - fitted**2
    spread = float(rise.std()) * np.sqrt(len(rise))
    return float(rise.sum() / spread) if spread > 0 else 0.0


def unconfirmed(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    pairs: IntArray,
    which: Sequence[int],
    *,
    bank: SurfaceBank | None = None,
) -> dict[int, float]:
    """Of the patches ``which``, those whose texture does not confirm where ``transforms``
    (``T_mosaic_patch``) put them over the overlapping ``pairs`` (k, 2): the rise of
    :func:`moved_misfit_rise` below :data:`CONFIRMS`, or none measurable; with their rise.
    ``bank``: the patches' raw heights as surfaces, if already built."""
    if not len(which):
        return {}
    bank, state = placement(patches, transforms, bank)
    out = {}
    for c in which:
        # a rise of CONFIRMS answers the question: the longer moves are not tried (a patch
        # left unconfirmed tries them all, so its rise is the same)
        rise = moved_misfit_rise(bank, state, pairs, int(c), enough=CONFIRMS)
        if not rise >= CONFIRMS:
            out[int(c)] = rise
    return out


def placement(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    bank: SurfaceBank | None = None,
) -> tuple[SurfaceBank, MosaicState]:
    """The patches' raw heights as surfaces (``bank``, if already built) and where
    ``transforms`` put them, in the bank's units (the median pixel's smaller side)."""
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    if bank is None:
        bank = SurfaceBank(patches, scale, 0.0, 1)
    return bank, MosaicState.from_transforms(transforms, bank, scale)
