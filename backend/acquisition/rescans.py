"""Re-scans: the quality gate's verdicts (and the operator's marks) turned into patches to scan
again, and the spoiling faults injected into a simulated run's chosen patches.

Verdicts come from the live merge's relay thread; the runner's worker thread alone acts on
them, between patches (:meth:`Rescans.apply`): a failed patch goes back to ``pending`` (its
scan kept aside in the run's file, :func:`backend.db.patch_store.reject_patch`) and is scanned
next, up to the run's ``rescan_max_tries``; after that it is ``flagged`` and left out of the
mosaic. Every decision is an event with its reason and a line in the run's ``rescans``.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from dataclasses import dataclass

from sqlalchemy.orm import Session

from backend.acquisition.journal import journaled_patch
from backend.acquisition.state import PatchStep
from backend.db.models import PatchRecord, Run
from backend.db.patch_store import reject_patch
from backend.events import EventBus


@dataclass(frozen=True)
class Verdict:
    """One word on one patch of one run: passed, or why not; ``operator`` marks a re-scan an
    operator asked for (it is done whatever the tries)."""

    run_id: int
    index: int
    passed: bool
    reason: str = ""
    operator: str | None = None


class Rescans:
    """Verdicts waiting for the worker, and the faults armed for simulated patches."""

    def __init__(self, events: EventBus) -> None:
        self.events = events
        self._verdicts: queue.Queue[Verdict] = queue.Queue()
        self._lock = threading.Lock()
        #: per patch index of the active or next run: the fault and how many scans it spoils
        #: (None: every one)
        self._spoil: dict[int, tuple[str, int | None]] = {}

    # -- from other threads --------------------------------------------------------------------

    def tell(self, verdict: Verdict) -> None:
        """A verdict for the worker to act on at its next patch boundary."""
        self._verdicts.put(verdict)

    def arm(self, kind: str, indices: list[int], count: int | None) -> None:
        """Spoil the scans of patches ``indices`` of the active or next run with ``kind``,
        ``count`` times each (None: every try)."""
        with self._lock:
            for index in indices:
                self._spoil[index] = (kind, count)

    def disarm(self) -> None:
        """No patch is spoiled any more."""
        with self._lock:
            self._spoil.clear()

    def spoiling(self, index: int) -> str | None:
        """The fault to spoil this scan of patch ``index`` with (counted), if any."""
        with self._lock:
            armed = self._spoil.get(index)
            if armed is None:
                return None
            kind, left = armed
            if left is not None:
                if left <= 1:
                    del self._spoil[index]
                else:
                    self._spoil[index] = (kind, left - 1)
            return kind

    # -- on the worker thread ------------------------------------------------------------------

    def apply(self, session: Session, run: Run, todo: deque[int]) -> list[int]:
        """Act on every verdict waiting for ``run``: record the passes, put failed patches at
        the front of ``todo`` (or flag them); return the indices taken out of the mosaic."""
        removed: list[int] = []
        records = {p.index: p for p in run.patches}
        while True:
            try:
                verdict = self._verdicts.get_nowait()
            except queue.Empty:
                break
            patch = records.get(verdict.index)
            if verdict.run_id != run.id or patch is None:
                continue
            if verdict.passed:
                if patch.quality is None:
                    patch.quality, patch.quality_reason = "ok", None
                continue
            if patch.step != PatchStep.STORED.value:
                continue  # already on its way to a re-scan
            if self._rescan(session, run, patch, verdict, todo):
                removed.append(patch.index)
        session.commit()
        return removed

    def _rescan(
        self, session: Session, run: Run, patch: PatchRecord, verdict: Verdict, todo: deque[int]
    ) -> bool:
        """Re-scan ``patch`` if the run's policy (or an operator) says so, else flag it;
        whether it went back to pending."""
        reason = verdict.reason or "marked for re-scan"
        if verdict.operator is None and not (
            run.rescan_enabled and patch.tries < run.rescan_max_tries
        ):
            patch.quality, patch.quality_reason = "flagged", reason[:500]
            tries = f"after {patch.tries} tries" if run.rescan_enabled else "(re-scans are off)"
            self.events.emit(
                "rescan",
                f"run {run.id}: patch {patch.index} flagged {tries}: {reason}",
                run_id=run.id,
                data={"patch": patch.index, "quality": "flagged", "reason": reason},
            )
            return False
        reject_patch(run.file, patch.index, patch.tries)
        who = f" (asked by {verdict.operator})" if verdict.operator else ""
        journaled_patch(session, self.events, run, patch).go(
            PatchStep.PENDING, reason=f"re-scan{who}: {reason}"
        )
        patch.stored_at, patch.dataset = None, None
        patch.quality, patch.quality_reason = "rescanned", reason[:500]
        run.rescans = [
            *run.rescans,
            {"index": patch.index, "try": patch.tries + 1, "reason": reason},
        ]
        if patch.index in todo:
            todo.remove(patch.index)
        todo.appendleft(patch.index)
        self.events.emit(
            "rescan",
            f"run {run.id}: patch {patch.index} to be scanned again (try {patch.tries + 1}){who}: "
            f"{reason}",
            run_id=run.id,
            data={"patch": patch.index, "try": patch.tries + 1, "reason": reason},
        )
        return True
