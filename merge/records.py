"""The records the merge's steps hand each other (:mod:`merge.pipeline`): the layout, the start's
placement, the solver's solution, and a stopwatch for the steps' wall times."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.transforms import PatchTransform
from merge.refine import RefineResult, SurfaceBank
from merge.refine.normal_system import NormalSystem

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class Layout:
    """What the merge knows before any stage: the patches' nominal footprints and overlaps.

    boxes : (n, 4) nominal footprints ``(xmin, ymin, xmax, ymax)``, metres.
    pairs : (k, 2) patch pairs that can overlap within the stage's error ``max_shift``.
    linked : (n,) whether each patch is in any pair.
    cell, max_shift : the refinement's raster spacing and the searched stage error, metres.
    warnings : patches that overlap nothing, groups that overlap no other group.
    """

    boxes: FloatArray
    pairs: IntArray
    linked: NDArray[np.bool_]
    cell: float
    max_shift: float
    warnings: list[str]


@dataclass(frozen=True)
class Placement:
    """Where the start put every patch: ``T_mosaic_patch``, which patches it measured in XY
    along both axes (``measured_both``; patches that overlap nothing count as measured), and
    what it measured of each of the layout's pairs (``pair_information`` (k, 2, 2), 1 / m²;
    None where it measured no XY); ``repeat`` (k,), metres from each pair's shift to one as
    likely where the overlap repeats itself (infinite where none; None where no XY
    measured: :attr:`merge.start.CoarseStart.repeat`); ``alternatives`` (m, n, 3), metres,
    the translations of other placements the start's pairs allow as well
    (:attr:`merge.start.CoarseStart.alternatives`; None or m = 0: none)."""

    transforms: list[PatchTransform]
    measured_both: NDArray[np.bool_]
    pair_information: FloatArray | None = None
    repeat: FloatArray | None = None
    alternatives: FloatArray | None = None

    def alternative(self, i: int) -> Placement:
        """The ``i``-th alternative as a placement: the same patches with its translations
        (and the start's drift planes)."""
        if self.alternatives is None or not 0 <= i < len(self.alternatives):
            raise ValueError(f"no alternative placement {i}")
        transforms = [
            PatchTransform(t=t, slope=tr.slope, centre=tr.centre)
            for t, tr in zip(self.alternatives[i], self.transforms, strict=True)
        ]
        return Placement(transforms, self.measured_both, self.pair_information, self.repeat)

    @property
    def complete(self) -> bool:
        """Whether the start measured every patch's XY along both axes."""
        return bool(self.measured_both.all())


@dataclass(frozen=True)
class Solution:
    """The transforms the solver settled on and how it went; ``bank``, the refinement's raw
    surfaces, ``system``, its last step's system if that step settled the fit, and
    ``plane_sigma``, the drift planes' prior it solved with (all reused by the assessment), None
    for the other methods; ``unsettled``, the patches the refinement stopped before it had
    settled them (:class:`merge.refine.RefineResult`), or None; ``refined_only``, the patches
    the refinement placed that the start did not measure along both axes (their texture must
    confirm the place: :mod:`merge.report.confirmation`), or None; ``start_information``, what
    the start measured of each of the layout's pairs (:attr:`Placement.pair_information`: a
    chain of measured overlaps must tie a patch to the mosaic, :mod:`merge.report.ties`), or
    None."""

    transforms: list[PatchTransform]
    iterations: int = 0
    converged: bool = True
    history: tuple[float, ...] = ()
    bank: SurfaceBank | None = None
    system: NormalSystem | None = None
    plane_sigma: FloatArray | None = None
    unsettled: NDArray[np.bool_] | None = None
    refined_only: NDArray[np.bool_] | None = None
    start_information: FloatArray | None = None

    @classmethod
    def of_refinement(
        cls,
        fit: RefineResult,
        *,
        refined_only: NDArray[np.bool_] | None = None,
        start_information: FloatArray | None = None,
    ) -> Solution:
        """What :func:`merge.refine.refine` settled on; ``refined_only`` and
        ``start_information`` as the class says."""
        return cls(
            fit.transforms,
            fit.iterations,
            fit.converged,
            tuple(fit.history),
            fit.bank,
            fit.system,
            fit.plane_sigma,
            fit.unsettled,
            refined_only,
            start_information,
        )


class Stopwatch:
    """Wall time per named step, summed over repeats (``timings``, seconds)."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        """Time the body of the ``with`` block as step ``name``."""
        clock = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - clock
