"""The acquisition worker's patch loop: move, land, scan, retract, store each patch, hand it to
the live merge, and act on the quality gate's verdicts between patches (a failed patch scanned
again next). Mixed into :class:`backend.acquisition.runner.Runner`, whose worker thread alone
runs it.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sqlalchemy.orm import Session

from backend.acquisition.control import Abort, Control
from backend.acquisition.journal import journaled_patch, journaled_run
from backend.acquisition.rescans import Rescans, Verdict
from backend.acquisition.state import PatchStep, RunState, StateMachine
from backend.acquisition.status import read_instrument
from backend.db.models import PatchRecord, Run
from backend.db.patch_store import read_patch, write_patch
from backend.db.space import check_space
from backend.events import EventBus
from backend.live_merge import LiveMergeService, scan_record
from backend.merge_worker import PatchInput, patch_id
from hardware.errors import ProcedureError
from hardware.microscope import Microscope
from hardware.procedures import move_stage, retract, sample_origin
from merge.live.gate import ScanRecord, record_verdict

FloatArray = NDArray[np.float64]

#: Seconds the end of a run waits for the live merge to judge its last patches.
LIVE_DRAIN = 120.0
#: Last looks of the quality gate at the whole mosaic, each after the re-scans of the one
#: before.
FINAL_LOOKS = 2
#: Scans in a row whose own record fails them by lines lost or Z saturated stop the run: the
#: tip or the sample needs a look, not more scans.
BAD_SCANS_IN_A_ROW = 3


class PatchLoop:
    """The patch loop of a run (the runner holds the attributes declared here)."""

    microscope: Microscope
    events: EventBus
    data_dir: Path
    reserve: int
    patch_bytes: int
    rescans: Rescans
    live: LiveMergeService | None
    _snapshot: dict[str, Any]
    #: scans in a row of the run under way that their own record failed
    _bad_scans: int = 0
    #: whether the worker has the tip on the surface (from landing until retracted)
    tip_down: bool = False

    def _checkpoint(self, session: Session, run: Run, control: Control, *, may_pause: bool) -> None:
        """Between steps: honour an abort; a pause where ``may_pause`` (tip off the surface)."""
        with control.wake:
            if control.abort:
                raise Abort
            if not (control.pause and may_pause):
                return
            self._transition(session, run, RunState.PAUSED, "paused", control.actor)
            control.wake.wait_for(lambda: not control.pause or control.abort)
            if control.request() == "abort":
                raise Abort
            self._transition(session, run, RunState.RUNNING, "resumed", control.actor)

    def _run_patches(self, session: Session, run: Run, control: Control) -> None:
        """Every pending patch in order; a patch the quality gate fails is scanned again next
        (:mod:`backend.acquisition.rescans`); at the end, the last verdicts are waited for."""
        records = {p.index: p for p in run.patches}
        todo = deque(p.index for p in run.patches if p.step != PatchStep.STORED.value)
        self._bad_scans = 0
        self._seed_live(run)
        looks = 0
        while True:
            while todo:
                self._scan_patch(session, run, control, records[todo.popleft()])
                self._act_on_verdicts(session, run, todo)
            live = self.live
            if live is None or not self._await_verdicts(live, session, run, control):
                return
            self._act_on_verdicts(session, run, todo)
            if todo:
                continue
            # every patch judged: the gate's last look, each with all its neighbours there
            if looks >= FINAL_LOOKS or not live.final(run.id, LIVE_DRAIN):
                return
            looks += 1
            self._act_on_verdicts(session, run, todo)
            if not todo:
                return

    def _await_verdicts(
        self, live: LiveMergeService, session: Session, run: Run, control: Control
    ) -> bool:
        """At the end: wait (at most :data:`LIVE_DRAIN` s, an abort or a pause honoured, the
        tip being off the surface) until the live merge judged every patch; whether it did."""
        deadline = time.monotonic() + LIVE_DRAIN
        while not live.drain(run.id, 0.2):
            self._checkpoint(session, run, control, may_pause=True)
            if time.monotonic() > deadline:
                return False
        return True

    def _seed_live(self, run: Run) -> None:
        """A run started again: its patches already stored go into the live merge first."""
        if self.live is None:
            return
        for patch in run.patches:
            if patch.step == PatchStep.STORED.value and patch.quality != "flagged":
                stored = read_patch(run.file, patch.index)
                record = scan_record(
                    stored.heights,
                    saturated=int(stored.attrs.get("saturated_lines", 0)),
                    mistracked=int(stored.attrs.get("mistracked_lines", 0)),
                )
                self._to_live(run, patch, stored.heights, stored.origin, stored.pixel_size, record)

    def _to_live(
        self,
        run: Run,
        patch: PatchRecord,
        heights: FloatArray,
        origin: tuple[float, float],
        pixel_size: tuple[float, float],
        record: ScanRecord,
    ) -> None:
        """Hand a stored patch, with what its scan recorded, to the run's live merge."""
        if self.live is None:
            return
        self.live.submit(
            run.id,
            PatchInput(
                patch_id(patch.index),
                heights,
                origin,
                pixel_size,
                patch.index,
                patch.row,
                patch.col,
            ),
            record,
        )

    def _act_on_verdicts(self, session: Session, run: Run, todo: deque[int]) -> None:
        """Act on the quality gate's verdicts (a re-scan keeps the failed scan aside in the
        file, so the disk is checked first: HDF5 must never meet a full disk)."""
        check_space(self.data_dir, need=self.patch_bytes, reserve=self.reserve)
        for index in self.rescans.apply(session, run, todo):
            if self.live is not None:
                self.live.remove(run.id, index)

    def _scan_patch(self, session: Session, run: Run, control: Control, patch: PatchRecord) -> None:
        """One patch: move, land, scan, retract, store; then hand it to the live merge."""
        m = self.microscope
        _, loop, scanner = m.require_afm()
        size = (run.patch_width, run.patch_height)
        pixels = (run.pixels_x, run.pixels_y)
        total = len(run.patches)
        machine = self._patch_machine(session, run, patch)
        planned = (patch.origin_x, patch.origin_y)
        self._checkpoint(session, run, control, may_pause=True)
        check_space(self.data_dir, need=self.patch_bytes, reserve=self.reserve)
        run.current_patch = patch.index
        patch.tries += 1
        machine.go(PatchStep.MOVE)
        move_stage(m.stage_x, m.stage_y, m.robot_x, m.robot_y, origin=planned, size=size)
        scanner.prepare(size=size, pixels=pixels)
        self._checkpoint(session, run, control, may_pause=True)
        machine.go(PatchStep.LAND)
        self.tip_down = True
        landing = m.land()
        self._checkpoint(session, run, control, may_pause=False)
        spoil = self.rescans.spoiling(patch.index) if m.sim is not None else None
        if spoil is not None and m.sim is not None:
            m.sim.spoil_next_scan(spoil, lines=run.pixels_y)
        machine.go(PatchStep.SCAN, reason=f"spoiled by a simulated {spoil}" if spoil else "")
        lines = scanner.scan(
            size=size, pixels=pixels, line_rate=run.line_rate, stop=lambda: control.abort
        )
        machine.go(PatchStep.RETRACT)
        retract(m.robot_z, loop)
        self.tip_down = False
        if self.live is None:  # no quality gate to judge clipped lines: as before, stop
            lines.require_unsaturated()
        origin = sample_origin(
            lines, m.stage_x, m.stage_y, planned=planned, size=size, x=m.robot_x, y=m.robot_y
        )
        name = write_patch(
            run.file,
            patch.index,
            lines.heights,
            origin=origin,
            pixel_size=lines.pixel_size,
            line_times=lines.line_times,
            attrs={
                "planned_origin": planned,
                "row": patch.row,
                "col": patch.col,
                "frequency_shift": landing.frequency_shift,
                "landing_cycles": landing.cycles,
                "line_rate": run.line_rate,
                "instrument": m.description,
                "try": patch.tries,
                "saturated_lines": lines.saturated_lines(),
                "mistracked_lines": lines.mistracked_lines(),
                "row_readings": lines.row_readings
                if lines.row_readings is not None
                else np.zeros(0),
            },
        )
        patch.dataset = name
        machine.go(PatchStep.STORED)
        self._snapshot = {
            **read_instrument(self.microscope),
            "last_patch": patch.index,
        }
        stored = sum(p.step == PatchStep.STORED.value for p in run.patches)
        self.events.emit(
            "progress",
            f"run {run.id}: patch {patch.index} stored ({stored}/{total})",
            run_id=run.id,
            data={"stored": stored, "total": total, "patch": patch.index},
        )
        record = scan_record(
            lines.heights,
            saturated=lines.saturated_lines(),
            mistracked=lines.mistracked_lines(),
        )
        said = record_verdict(record)
        if said.ok or self.live is None:  # no gate: no re-scans (Z saturated stopped above)
            self._bad_scans = 0
            self._to_live(run, patch, lines.heights, origin, lines.pixel_size, record)
            return
        # a run stops on the instrument's unambiguous signs only (lines lost, Z saturated)
        bad = not record_verdict(record, tracking=False).ok
        self._bad_scans = self._bad_scans + 1 if bad else 0
        if self._bad_scans >= BAD_SCANS_IN_A_ROW:
            raise ProcedureError(
                f"{self._bad_scans} scans in a row failed their own record (the last, patch "
                f"{patch.index}: {said.reason}): check the tip and the sample before going on"
            )
        self.rescans.tell(Verdict(run.id, patch.index, False, said.reason))

    def _patch_machine(
        self, session: Session, run: Run, patch: PatchRecord
    ) -> StateMachine[PatchStep]:
        return journaled_patch(session, self.events, run, patch)

    def _transition(
        self, session: Session, run: Run, target: RunState, reason: str, actor: str
    ) -> None:
        journaled_run(session, self.events, run).go(target, reason=reason, actor=actor)
