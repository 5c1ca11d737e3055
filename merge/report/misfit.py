"""How a patch lies over each patch it overlaps: residual RMS and sudden Z steps, pair by pair.

A spoiled patch lies badly over all its neighbours; a good patch next to a spoiled one lies
badly over that one only. So the quality gate (:mod:`merge.live.gate`) reads the misfit pair
by pair (:func:`pair_misfits`) to tell which of the two to scan again.

A Z jump mid-patch (the sample or the scanner slips) leaves every line after it offset: the
drift plane takes a part of it, the scan lines' offsets model (:mod:`merge.refine.lines`) lets
each line's residuals move together, and the residual RMS rises by only about twice. Over a
neighbour, though, the patch's line by line median residual is then a step, whatever the
sample's own texture (the neighbour holds the same texture). The step is fitted at every
possible line with a straight line beside it (the drift plane's share), and the largest is
kept with its standard error (:class:`LineStep`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.rows import residuals
from merge.refine.state import MosaicState

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Fewest lines on either side of a step (fewer: a bend at the end, not a step).
MIN_SIDE = 4
#: Fewest residuals a line needs to have a mean.
MIN_POINTS = 8


@dataclass(frozen=True)
class LineStep:
    """The largest step in a patch's line-mean residuals: its height (metres), its standard
    error (metres) and the first line after it; ``lines`` had a mean."""

    height: float
    sigma: float
    line: int
    lines: int

    @property
    def significance(self) -> float:
        """The step in standard errors (0 where none could be fitted)."""
        return abs(self.height) / self.sigma if self.sigma > 0 else 0.0


@dataclass(frozen=True)
class PairMisfit:
    """How patch ``c``'s points lie over one other patch: ``other`` (its index), the RMS of
    their heights above its surface (metres), how many there were, the largest Z step between
    ``c``'s lines in them (:class:`LineStep`), and the box of mosaic XY they cover
    ``(xmin, ymin, xmax, ymax)``, metres."""

    other: int
    rms: float
    points: int
    step: LineStep
    box: tuple[float, float, float, float]


def pair_misfits(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    pairs: IntArray,
    c: int,
) -> list[PairMisfit]:
    """Patch ``c`` against each patch it overlaps, one :class:`PairMisfit` per pair.

    Parameters
    ----------
    patches : sequence of Patch
    transforms : sequence of PatchTransform
        ``T_mosaic_patch`` per patch.
    pairs : (k, 2) int array
        Pairs that overlap at those transforms; those with ``c`` count.
    c : int
        The patch judged.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    mine = pairs[(pairs == c).any(axis=1)]
    if not len(mine):
        return []
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    bank = SurfaceBank(patches, scale, 0.0, 1)
    state = MosaicState.from_transforms(transforms, bank, scale)
    margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
    rows = bank.rows(bank.candidates(mine, state.R, state.s, margin))
    r, valid, _, _ = residuals(bank, rows, state)
    own = (rows.src == c) & valid  # c's points over the others' surfaces
    lines = patches[c].heights.shape[0]
    points = np.nan_to_num(bank.point_xyz(rows))
    world = (points @ state.R[c, :2].T + state.s[c, :2]) * scale
    out = []
    for j in np.unique(rows.dst[own]).tolist():
        here = own & (rows.dst == j)
        value = r[here] * scale
        means = _line_means(rows.row[here], value, lines)
        rms = float(np.sqrt(np.mean(value**2)))
        lo, hi = world[here].min(axis=0), world[here].max(axis=0)
        box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        out.append(PairMisfit(int(j), rms, int(here.sum()), _largest_step(means), box))
    return out


def _line_means(line_of: IntArray, value: FloatArray, lines: int) -> FloatArray:
    """Per scan line (of ``lines``), the median of the ``value`` of its points (NaN where
    fewer than :data:`MIN_POINTS`)."""
    out = np.full(lines, np.nan)
    order = np.argsort(line_of, kind="stable")
    bounds = np.searchsorted(line_of[order], np.arange(lines + 1))
    for line in range(lines):
        here = value[order[bounds[line] : bounds[line + 1]]]
        if len(here) >= MIN_POINTS:
            out[line] = float(np.median(here))
    return out


def _largest_step(means: FloatArray) -> LineStep:
    """The step, with a straight line beside it (the drift plane's share), that best fits
    ``means`` (per line, NaN: none), over every split with :data:`MIN_SIDE` lines a side."""
    lines = np.flatnonzero(np.isfinite(means))
    m = means[lines]
    none = LineStep(0.0, math.inf, 0, len(lines))
    if len(lines) < 2 * MIN_SIDE + 1:
        return none
    t = (lines - lines.mean()) / max(float(np.ptp(lines)), 1.0)
    best = none
    for k in range(MIN_SIDE, len(lines) - MIN_SIDE + 1):
        step = (np.arange(len(lines)) >= k).astype(np.float64)
        A = np.column_stack([np.ones(len(lines)), t, step])
        coef, *_ = np.linalg.lstsq(A, m, rcond=None)
        resid = m - A @ coef
        dof = len(lines) - 3
        # a robust scale: the lines' own scatter, not dragged up by the step it misses
        s2 = (1.4826 * float(np.median(np.abs(resid - np.median(resid))))) ** 2
        s2 = max(s2, float(resid @ resid) / dof * 1e-6, 1e-30)
        cov = s2 * np.linalg.inv(A.T @ A)
        candidate = LineStep(float(coef[2]), float(np.sqrt(cov[2, 2])), int(lines[k]), len(lines))
        if candidate.significance > best.significance:
            best = candidate
    return best
