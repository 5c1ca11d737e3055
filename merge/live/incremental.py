"""The incremental merge: patches added one at a time to a mosaic kept solved.

Adding patch ``c`` (:meth:`LiveMerge.add`):

1. its neighbours: the stored patches its nominal footprint can overlap within the stage's
   error;
2. its coarse start against them (:func:`merge.start.coarse_start` on ``c`` and its
   neighbours), placed where its neighbours now are: the start's translations are relative,
   so ``c`` goes where the neighbours' refined places say, their centres' offsets averaged
   (a neighbour that its own start measured along one axis only, an edge's, and that this
   start measures along both is placed again the same way);
3. a refinement of the neighbourhood it touches: ``c`` and its neighbours move, the patches
   around them are held where they are (:func:`merge.refine.refine` with ``held``);
4. every ``full_every`` patches (:meth:`LiveMerge.polish`, when the caller has time) and at
   the end (:meth:`LiveMerge.result`), a full simultaneous refinement of all patches from
   where they are.

The live mosaic is kept on a canvas (:mod:`merge.live.canvas`) where only the patches that
moved are drawn again.

It stays a simultaneous multi-view solution, never a chain: each neighbourhood is solved
together, and the full refinements solve the whole mosaic at once, so the end result is the
batch merge's (:func:`merge.run`) within the noise. The cost of an addition depends on the
neighbourhood, not on the mosaic; the full refinements start converged and polish.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from merge.config import MergeConfig
from merge.core.errors import MergeCancelled
from merge.core.overlap import moved_boxes, overlapping_pairs
from merge.core.parallel import one_blas_thread
from merge.core.patchset import Patch, PatchSet
from merge.core.transforms import PatchTransform
from merge.finish import finish
from merge.live.canvas import LiveCanvas
from merge.live.neighbourhood import frame_offset, nominal_neighbours, to_place, within
from merge.pipeline import (
    SHIFT_PRIOR_FRACTION,
    default_cell,
    default_max_shift,
    layout_of,
    periodic_warnings,
)
from merge.records import Solution, Stopwatch
from merge.refine import DEFAULT_LEVELS, Level, RefineResult, refine
from merge.render import Mosaic
from merge.report import MergeResult, PatchFit, assess
from merge.report.misfit import PairMisfit, pair_misfits
from merge.start import coarse_cell, coarse_start

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Full simultaneous refinement of every patch after this many additions (and at the end).
FULL_EVERY = 10


@dataclass(frozen=True)
class LiveUpdate:
    """What one addition did.

    id : the patch added (or replaced).
    neighbours : ids of the stored patches it can overlap.
    registered : whether its coarse start measured its XY against them.
    measurable : whether any of its overlaps could be correlated (texture on both sides):
        measurable and not registered, the overlaps should have registered and did not.
    fits : the quality of every patch of the neighbourhood refined, by id
        (:class:`merge.report.PatchFit`, against the patches around it).
    misfits : how it lies over each neighbour, by the neighbour's id
        (:func:`merge.report.misfit.pair_misfits`: residual RMS and Z steps).
    seconds : wall time of the addition, by step (``start``, ``refine``, ``report``,
        ``render``).
    """

    id: str
    neighbours: tuple[str, ...]
    registered: bool
    measurable: bool
    fits: dict[str, PatchFit]
    misfits: dict[str, PairMisfit] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


class LiveMerge:
    """A mosaic merged patch by patch while it is scanned.

    Parameters
    ----------
    config : MergeConfig, optional
        The merge's options (the default method; ``cell``, ``max_shift``, ``pixel_size`` and
        ``feather`` are honoured as by :func:`merge.run`).
    full_every : int, keyword-only
        Additions after which a full simultaneous refinement is due (:meth:`polish`; default
        :data:`FULL_EVERY`).

    :meth:`add` refines only the neighbourhood a patch touches, so its cost does not grow
    with the mosaic; :meth:`polish` runs the full refinement when it is due, and may be
    cancelled (a caller runs it while it waits for the next patch, and stops it when one
    comes); :meth:`result` refines all to convergence and reports as :func:`merge.run` does.
    """

    def __init__(self, config: MergeConfig | None = None, *, full_every: int = FULL_EVERY):
        self.config = config or MergeConfig()
        if self.config.method != "default":
            raise ValueError(f"the live merge runs the default method, not {self.config.method!r}")
        if full_every < 1:
            raise ValueError(f"full_every must be >= 1, got {full_every}")
        self.full_every = full_every
        self.patches: list[Patch] = []
        self.transforms: list[PatchTransform] = []
        #: per patch, whether a coarse start measured its XY along both axes
        self.complete: list[bool] = []
        #: every coarse start's pairs: how far each repeats itself, and what it measured
        self.repeats: list[tuple[FloatArray, FloatArray]] = []
        self.canvas: LiveCanvas | None = None
        self._since_full = 0

    # -- what it holds ----------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.patches)

    @property
    def ids(self) -> list[str]:
        """Patch ids in the order they were added."""
        return [p.id for p in self.patches]

    @property
    def full_due(self) -> bool:
        """Whether enough patches came since the last full refinement for another."""
        return self._since_full >= self.full_every and len(self.patches) > 2

    def mosaic(self) -> Mosaic:
        """The live mosaic: every patch through its current transform."""
        if self.canvas is None or not self.patches:
            raise ValueError("the live merge holds no patch yet")
        return self.canvas.mosaic()

    # -- changes ----------------------------------------------------------------------------

    @one_blas_thread()
    def add(self, patch: Patch) -> LiveUpdate:
        """Add ``patch`` and refine its neighbourhood; a patch of an id already held replaces
        it (a re-scan)."""
        if patch.id in self.ids:
            self.remove(patch.id)
        self.patches.append(patch)
        self.transforms.append(PatchTransform())
        self.complete.append(False)
        c = len(self.patches) - 1
        watch = Stopwatch()
        with watch.step("start"):
            neighbours, registered, measurable = self._start(c)
        fits: dict[str, PatchFit] = {}
        misfits: dict[str, PairMisfit] = {}
        moved = np.array([c])
        if len(neighbours):
            with watch.step("refine"):
                members, moved = self._refine_around(c, neighbours)
            with watch.step("report"):
                fits, misfits = self._fits(members, c, neighbours)
        with watch.step("render"):
            self._draw(moved)
        self._since_full += 1
        return LiveUpdate(
            id=patch.id,
            neighbours=tuple(self.patches[j].id for j in neighbours),
            registered=registered,
            measurable=measurable,
            fits=fits,
            misfits=misfits,
            seconds=watch.timings,
        )

    def misfits_of(self, patch_id: str) -> dict[str, PairMisfit]:
        """How patch ``patch_id`` lies now over each patch it overlaps, by their ids (the final
        look of the quality gate, once every neighbour is there)."""
        return self._misfits(self.ids.index(patch_id), self._overlaps_now())

    def misfits(self) -> dict[str, dict[str, PairMisfit]]:
        """:meth:`misfits_of` every patch, the overlaps found once for all."""
        pairs = self._overlaps_now()
        return {p.id: self._misfits(c, pairs) for c, p in enumerate(self.patches)}

    def _overlaps_now(self) -> IntArray:
        """The pairs of patches that overlap at their current transforms."""
        cell = self.config.cell or default_cell(self.patches)
        boxes = moved_boxes(np.array([p.footprint for p in self.patches]), self.transforms)
        return overlapping_pairs(boxes, margin=cell)

    def _misfits(self, c: int, pairs: IntArray) -> dict[str, PairMisfit]:
        near = np.unique(pairs[(pairs == c).any(axis=1)])
        members = np.concatenate([[c], near[near != c]]).astype(np.intp)
        local = [self.patches[int(j)] for j in members]
        placed = [self.transforms[int(j)] for j in members]
        found = pair_misfits(local, placed, within(members, pairs), 0)
        return {local[m.other].id: m for m in found}

    def remove(self, patch_id: str) -> None:
        """Leave out the patch ``patch_id`` (a flagged patch, or one about to be re-scanned)."""
        k = self.ids.index(patch_id)
        if self.canvas is not None:
            self.canvas.erase(patch_id)
        del self.patches[k]
        del self.transforms[k]
        del self.complete[k]

    @one_blas_thread()
    def polish(self, *, cancel: Callable[[], bool] | None = None) -> bool:
        """The full simultaneous refinement of every patch from where it is, if due; whether
        it ran to the end (a ``cancel`` that turns true stops it, the mosaic as it was)."""
        if not self.full_due:
            return False
        try:
            self._refine_all(DEFAULT_LEVELS[-1:], cancel=cancel)
        except MergeCancelled:
            return False
        self._draw(np.arange(len(self.patches)))
        return True

    @one_blas_thread()
    def result(self) -> MergeResult:
        """The final mosaic: a full refinement to convergence, the report and the render,
        as :func:`merge.run` returns them."""
        if len(self.patches) < 2:
            raise ValueError(f"need at least 2 patches to merge, have {len(self.patches)}")
        watch = Stopwatch()
        with watch.step("solve"):
            fit = self._refine_all(DEFAULT_LEVELS[1:], report=True)
        solution = Solution(list(self.transforms))
        if fit is not None:
            # the patches no start measured both ways: their texture must confirm the place
            loose = ~np.array(self.complete, dtype=bool)
            solution = Solution.of_refinement(fit, refined_only=loose if loose.any() else None)
        layout = layout_of(PatchSet(self.patches), self.config)
        if self.repeats:  # a periodic sample, as the starts saw it
            repeat, information = (np.concatenate(a) for a in zip(*self.repeats, strict=True))
            layout = replace(
                layout, warnings=layout.warnings + periodic_warnings(repeat, information)
            )
        return finish(self.patches, layout, solution, self.config, watch)

    def _refine_all(
        self,
        levels: Sequence[Level],
        *,
        cancel: Callable[[], bool] | None = None,
        report: bool = False,
    ) -> RefineResult | None:
        """Every patch refined at once from where it is, over ``levels`` (a cancel raises
        :class:`merge.MergeCancelled` and changes nothing); what it did (None: nothing to
        refine). ``report``: as :func:`merge.refine.refine`'s."""
        if len(self.patches) < 2:
            return None
        cell = self.config.cell or default_cell(self.patches)
        max_shift = self.config.max_shift or default_max_shift(self.patches)
        boxes = np.array([p.footprint for p in self.patches])
        near = overlapping_pairs(moved_boxes(boxes, self.transforms), margin=4.0 * cell)
        if not len(near):  # nothing overlaps: nothing to refine
            self._since_full = 0
            return None
        fit = refine(
            self.patches,
            near,
            self.transforms,
            levels=levels,
            shift_prior=SHIFT_PRIOR_FRACTION * max_shift,
            cancel=cancel,
            measured=np.array(self.complete, dtype=bool),
            report=report,
        )
        self.transforms = list(fit.transforms)
        self._since_full = 0
        return fit

    def _draw(self, which: IntArray) -> None:
        """The patches ``which`` drawn on the canvas at their current transforms."""
        if self.canvas is None:
            pitch = self.config.pixel_size or (
                min(p.pixel_size[0] for p in self.patches),
                min(p.pixel_size[1] for p in self.patches),
            )
            self.canvas = LiveCanvas(pitch, feather=self.config.feather)
        for j in which.tolist():
            self.canvas.draw(self.patches[j], self.transforms[j])

    # -- the steps of an addition -----------------------------------------------------------

    def _start(self, c: int) -> tuple[IntArray, bool, bool]:
        """Steps 1 and 2: ``c``'s neighbours and its coarse start among them, placed where
        they now are; whether its XY was measured, and whether it could have been."""
        cell = self.config.cell or default_cell(self.patches)
        max_shift = self.config.max_shift or default_max_shift(self.patches)
        neighbours = nominal_neighbours(np.array([p.footprint for p in self.patches]), c, max_shift)
        if not len(neighbours):
            return neighbours, False, False
        members = np.concatenate([neighbours, [c]])
        local = [self.patches[int(j)] for j in members]
        boxes = np.array([p.footprint for p in local])
        pairs = overlapping_pairs(boxes, margin=max_shift)
        start = coarse_start(
            local,
            pairs,
            cell=self.config.coarse_cell or coarse_cell(local, cell),
            max_shift=max_shift,
        )
        self.repeats.append((start.repeat, start.pair_information))
        # the patches to place (c, and neighbours first measured both ways now) and the frame
        complete = start.xy_complete
        known = np.array([self.complete[int(j)] for j in neighbours] + [False])
        moving, reference = to_place(complete, known)
        shift = frame_offset(
            [local[k] for k in np.flatnonzero(reference)],
            start.translation[reference],
            [self.transforms[int(members[k])] for k in np.flatnonzero(reference)],
        )
        for k in np.flatnonzero(moving).tolist():
            j = int(members[k])
            self.transforms[j] = PatchTransform(
                t=start.translation[k] + shift,
                slope=-start.tilt[k],
                centre=np.array(local[k].center),
            )
            self.complete[j] = bool(complete[k])
        return neighbours, bool(start.xy_measured[-1]), bool(start.xy_measurable[-1])

    def _refine_around(self, c: int, neighbours: IntArray) -> tuple[IntArray, IntArray]:
        """Step 3: ``c`` and its neighbours refined together, the patches around them held;
        the indices of all patches in that refinement (free first), and of those it moved."""
        cell = self.config.cell or default_cell(self.patches)
        max_shift = self.config.max_shift or default_max_shift(self.patches)
        free = np.concatenate([neighbours, [c]])
        boxes = moved_boxes(np.array([p.footprint for p in self.patches]), self.transforms)
        near = overlapping_pairs(boxes, margin=4.0 * cell)
        on_free = np.isin(near, free).any(axis=1)
        ring = np.setdiff1d(np.unique(near[on_free]), free)
        if not len(ring):  # nothing around to hold the gauge: the oldest neighbour holds it
            ring, free = free[:1], free[1:]
        members = np.concatenate([free, ring])
        sub_pairs = within(members, near)
        held = np.zeros(len(members), dtype=bool)
        held[len(free) :] = True
        # the widest level for patches no start measured both ways, as the batch merge does
        complete = np.array([self.complete[int(j)] for j in members], dtype=bool)
        loose = ~complete & ~held
        fit = refine(
            [self.patches[int(j)] for j in members],
            sub_pairs,
            [self.transforms[int(j)] for j in members],
            levels=DEFAULT_LEVELS if loose.any() else DEFAULT_LEVELS[1:],
            shift_prior=SHIFT_PRIOR_FRACTION * max_shift,
            held=held,
            first_free=loose if loose.any() else None,
            measured=complete,
        )
        for k, j in enumerate(members[: len(free)]):
            self.transforms[int(j)] = fit.transforms[k]
        return members, free

    def _fits(
        self, members: IntArray, c: int, neighbours: IntArray
    ) -> tuple[dict[str, PatchFit], dict[str, PairMisfit]]:
        """The quality of ``c`` and its neighbours against everything in the neighbourhood,
        and how ``c`` lies over each patch it overlaps."""
        patches = [self.patches[int(j)] for j in members]
        transforms = [self.transforms[int(j)] for j in members]
        cell = self.config.cell or default_cell(patches)
        boxes = moved_boxes(np.array([p.footprint for p in patches]), transforms)
        pairs = overlapping_pairs(boxes, margin=cell)
        fits = assess(patches, pairs, transforms)
        wanted = {int(j) for j in neighbours} | {c}
        by_id = {
            self.patches[int(j)].id: fits[k] for k, j in enumerate(members) if int(j) in wanted
        }
        own = int(np.flatnonzero(members == c)[0])
        misfits = {patches[m.other].id: m for m in pair_misfits(patches, transforms, pairs, own)}
        return by_id, misfits
