"""Two fits of the same patches compared on the points both of them overlap.

The residual RMS of a fit is taken over the points that overlap in it, and a fit that moves a
patch off its neighbours, even in part, sheds the misfit of the points it no longer overlaps: a
lower RMS over fewer points is no sign of a better placement. Nor are fewer points a sign of a
worse one (a block of patches put back where it belongs often overlaps less than the wrong
correlation peaks had it: the pairs' correlation favours the larger overlap). On the points both
fits overlap the two explain the same heights, and the one that leaves them less misfit is the
better (:func:`common_misfit`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.rows import residuals
from merge.refine.state import MosaicState

IntArray = NDArray[np.intp]

#: Directed pairs whose points are looked up at once (bounds the rows held in memory).
RUNS_AT_ONCE = 256


@dataclass(frozen=True)
class CommonMisfit:
    """Two fits on the points both overlap: how many there are, and the sum of their squared
    residuals (heights above the other patch's surface, m²) in the fit ``before`` and in the fit
    ``after``."""

    points: int
    before: float
    after: float

    @property
    def ratio(self) -> float:
        """Residual RMS of ``after`` over that of ``before`` on the common points (1 if none)."""
        return float(np.sqrt(self.after / self.before)) if self.before > 0 else 1.0

    @property
    def evidence(self) -> float:
        """What ``after`` explains better than ``before``: the drop of the squared residuals'
        sum in units of ``before``'s mean square residual (points' worth of misfit; negative
        where ``after`` fits worse)."""
        if self.before <= 0:
            return 0.0
        return self.points * (1.0 - self.after / self.before)


def common_misfit(
    bank: SurfaceBank,
    pairs: IntArray,
    before: Sequence[PatchTransform],
    after: Sequence[PatchTransform],
    *,
    scale: float,
) -> CommonMisfit:
    """The fits ``before`` and ``after`` (``T_mosaic_patch`` per patch of ``bank``) on the
    points that overlap in both.

    Parameters
    ----------
    bank : SurfaceBank
        The patches' raw heights as surfaces, lengths in units of ``scale``.
    pairs : (k, 2) int array
        Pairs of patches that may overlap in either fit (both ways are counted).
    before, after : sequence of PatchTransform
        The two fits.
    scale : float
        The bank's length unit, metres.
    """
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    if len(before) != len(after) or len(before) != len(bank.nx):
        raise ValueError(
            f"two fits of {len(bank.nx)} patches are compared, got {len(before)} and "
            f"{len(after)} transforms"
        )
    first = MosaicState.from_transforms(before, bank, scale)
    second = MosaicState.from_transforms(after, bank, scale)
    margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
    # a point both fits overlap overlaps in ``before``: its rows hold them all
    runs = bank.candidates(pairs, first.R, first.s, margin)
    points, sum_before, sum_after = 0, 0.0, 0.0
    for lo in range(0, len(runs), RUNS_AT_ONCE):
        rows = bank.rows(runs, lo, min(lo + RUNS_AT_ONCE, len(runs)))
        r_before, ok_before, _, _ = residuals(bank, rows, first)
        r_after, ok_after, _, _ = residuals(bank, rows, second)
        both = ok_before & ok_after
        points += int(both.sum())
        sum_before += float(np.sum(r_before[both] ** 2))
        sum_after += float(np.sum(r_after[both] ** 2))
    return CommonMisfit(points, sum_before * scale**2, sum_after * scale**2)
