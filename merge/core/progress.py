"""Where a merge is (its stage and how far along the whole it is, for a progress bar and an
ETA), and where it stops when cancelled.

A large merge spends minutes in stages that have no iterations (the start correlates tens of
thousands of pairs; the report factorises the mosaic's system slab by slab; the render draws
every patch), so a per-iteration callback alone leaves a bar still for minutes and a cancel
unheard. :func:`tracking` (run by :func:`merge.run`) installs a :class:`Tracker` for the merge;
each stage opens with :func:`stage` and its loops call :func:`checkpoint`: it counts the work
done, reports it (at most every :data:`REPORT_EVERY` seconds, and at every stage), and raises
:class:`~merge.core.errors.MergeCancelled` once the caller's ``cancel()`` says so. The tracker
lives in a context variable, so the loops deep inside the stages need no extra argument, and a
merge outside :func:`tracking` (a test, the live merge's pieces) checks nothing.

The stages' shares of a merge's time (:data:`SHARES`) were measured on the folded surface's
mosaics from 400 to 2,500 patches of 64 x 64 px (the start 22-25 %, the refinement 51-57 %,
the report 14-16 %, the render 3-5 %); within a stage, its own units of work.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

from merge.core.errors import MergeCancelled

#: Each stage's share of a merge's time.
SHARES = {"start": 0.24, "refine": 0.56, "report": 0.15, "render": 0.05}
#: Seconds between two reports within a stage.
REPORT_EVERY = 0.25


@dataclass(frozen=True)
class Status:
    """Where a merge is: its ``stage`` (one of :data:`SHARES`), what within it (``detail``),
    the fraction of the whole merge done (0-1), and the seconds since it began."""

    stage: str
    detail: str
    fraction: float
    elapsed: float

    @property
    def eta(self) -> float | None:
        """Seconds still to go, from the pace so far (None before there is one)."""
        if self.fraction <= 0.02 or self.elapsed <= 0:
            return None
        return self.elapsed * (1.0 - self.fraction) / self.fraction


Report = Callable[[Status], None]


class Tracker:
    """One merge's progress: the stage, its units done of its total, and the caller's cancel."""

    def __init__(
        self,
        report: Report | None,
        cancel: Callable[[], bool] | None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.report = report
        self.cancel = cancel
        self.clock = clock
        self.began = clock()
        self.stage = ""
        self.detail = ""
        self.total = 1.0
        self.done = 0.0
        self.last = -float("inf")

    def fraction(self) -> float:
        """Of the whole merge, done: the stages before this one and this one's share."""
        before = 0.0
        for name, share in SHARES.items():
            if name == self.stage:
                return before + share * min(self.done / self.total, 1.0)
            before += share
        return before

    def enter(self, name: str, total: float, detail: str = "") -> None:
        if name not in SHARES:
            raise ValueError(f"stage must be one of {', '.join(SHARES)}, got {name!r}")
        self.stage, self.detail, self.total, self.done = name, detail, max(total, 1e-9), 0.0
        self.tell(force=True)

    def advance(self, units: float, detail: str | None = None) -> None:
        self.done += units
        if detail is not None:
            self.detail = detail
        self.tell(force=detail is not None)

    def tell(self, *, force: bool = False) -> None:
        now = self.clock()
        if not self.stage:  # a look for a cancel before the first stage: nothing done to tell
            return
        if self.report is not None and (force or now - self.last >= REPORT_EVERY):
            self.last = now
            self.report(Status(self.stage, self.detail, self.fraction(), now - self.began))

    def finish(self) -> None:
        """The merge is done: told once, at the whole."""
        self.stage, self.detail, self.done, self.total = list(SHARES)[-1], "done", 1.0, 1.0
        self.tell(force=True)

    def check(self) -> None:
        if self.cancel is not None and self.cancel():
            raise MergeCancelled("merge cancelled")


_current: ContextVar[Tracker | None] = ContextVar("merge_progress", default=None)


@contextmanager
def tracking(report: Report | None, cancel: Callable[[], bool] | None) -> Iterator[Tracker | None]:
    """Track the merge run in the ``with`` body: ``report`` told where it is, ``cancel`` polled
    at every :func:`checkpoint`. A merge run inside another's tracking keeps the outer one."""
    if _current.get() is not None or (report is None and cancel is None):
        yield _current.get()
        return
    tracker = Tracker(report, cancel)
    token = _current.set(tracker)
    try:
        yield tracker
        tracker.finish()
    finally:
        _current.reset(token)


@contextmanager
def stage(name: str, total: float = 1.0, detail: str = "") -> Iterator[None]:
    """The ``with`` body is stage ``name`` of :data:`SHARES`, ``total`` units of work."""
    tracker = _current.get()
    if tracker is not None:
        tracker.enter(name, total, detail)
        tracker.check()
    yield


def checkpoint(units: float = 0.0, detail: str | None = None) -> None:
    """``units`` more of the current stage done (``detail``: what it does now); raises
    :class:`~merge.core.errors.MergeCancelled` if the merge was cancelled. Nothing outside
    :func:`tracking`."""
    tracker = _current.get()
    if tracker is not None:
        tracker.advance(units, detail)
        tracker.check()
