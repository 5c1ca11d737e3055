"""Runs: plan, create, start, pause, resume, abort, reset; patches and their data."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Body, HTTPException, Query, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from backend.acquisition.planner import PatchSpec, Plan, PlanError, Roi, plan_mosaic
from backend.acquisition.state import RunState
from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.responses import NPY, PNG_RESPONSES, height_map, npy_response, png_response
from backend.api.schemas import (
    AbortIn,
    PatchIndex,
    PatchOut,
    PatchShapeOut,
    PlanIn,
    PlanOut,
    ProgressOut,
    RescanIn,
    RescanOut,
    ResetIn,
    RoiIn,
    RoiOut,
    RunId,
    RunOut,
    RunSemOut,
)
from backend.api.sem import calibration_out, stored_geometry
from backend.db.models import MergeJob, PatchRecord, Run, SemCalibrationRecord, SemImageRecord
from backend.db.patch_store import LIVE_GROUP, StoredPatch, read_merge, read_patch
from backend.services import Services
from merge.io.png import encode_png
from merge.io.preview import afm_colors, fit_size

router = APIRouter(prefix="/api/runs", tags=["runs"])

#: Seconds an abort waits for the safe state before it answers (the abort goes on).
ABORT_ANSWER = 0.8


def _plan(body: PlanIn, services: Services, session: Session) -> Plan:
    return _plan_on(body, services, session)[0]


def _plan_on(
    body: PlanIn, services: Services, session: Session
) -> tuple[Plan, SemImageRecord | None]:
    """The plan, and the SEM image its ROI was drawn on (None: drawn in stage metres)."""
    sem: SemImageRecord | None = None
    if body.sem_roi is not None:
        sem = session.get(SemImageRecord, body.sem_roi.sem_id)
        if sem is None:
            raise HTTPException(404, f"sem_roi.sem_id: no SEM image {body.sem_roi.sem_id}")
        r = body.sem_roi
        if r.col + r.width > sem.width or r.row + r.height > sem.height:
            raise HTTPException(
                422,
                f"sem_roi: the rectangle leaves the {sem.width} x {sem.height} px image",
            )
        roi = Roi.from_sem(stored_geometry(sem), r.col, r.row, r.width, r.height)
    elif body.roi is not None:
        roi = Roi(body.roi.x, body.roi.y, body.roi.width, body.roi.height)
    else:  # the schema already refuses this
        raise HTTPException(422, "give roi (stage metres) or sem_roi (SEM pixels)")
    patch = PatchSpec(body.patch.width, body.patch.height, body.patch.pixels)
    plan = plan_mosaic(roi, patch, body.overlap, limits=services.limits, line_rate=body.line_rate)
    return plan, sem


def _patch_out(p: PatchRecord) -> PatchOut:
    return PatchOut(
        index=p.index,
        row=p.row,
        col=p.col,
        origin=(p.origin_x, p.origin_y),
        step=p.step,
        stored_at=p.stored_at,
        quality=p.quality,  # type: ignore[arg-type]
        reason=p.quality_reason,
        tries=p.tries,
    )


def run_out(run: Run, services: Services, session: Session, *, patches: bool) -> RunOut:
    stored = sum(p.step == "stored" for p in run.patches)
    current = next((p for p in run.patches if p.step not in ("pending", "stored")), None)
    merges = session.scalars(
        select(MergeJob.id).where(MergeJob.run_id == run.id).order_by(MergeJob.id)
    ).all()
    # a run whose end the disk refused: the state the runner holds, not the stale row
    held = services.runner.unrecorded(run.id)
    state, message = held if held is not None else (run.state, run.message)
    damage: list[str] = []

    def number(name: str) -> float | None:
        value = getattr(run, name)
        if isinstance(value, int | float) and math.isfinite(value):
            return float(value)
        damage.append(f"{name} is {value!r}, not a finite number")
        return None

    return RunOut(
        id=run.id,
        state=state,
        created_at=run.created_at,
        updated_at=run.updated_at,
        roi=RoiOut(
            x=number("roi_x"),
            y=number("roi_y"),
            width=number("roi_width"),
            height=number("roi_height"),
        ),
        patch=PatchShapeOut(
            width=number("patch_width"),
            height=number("patch_height"),
            pixels=(run.pixels_x, run.pixels_y),
        ),
        overlap=(number("overlap_x"), number("overlap_y")),
        line_rate=number("line_rate"),
        damage=damage,
        rows=run.rows,
        cols=run.cols,
        instrument=run.instrument,
        created_by=run.created_by,
        started_by=run.started_by,
        progress=ProgressOut(stored=stored, total=len(run.patches)),
        current_patch=current.index if current else run.current_patch,
        current_step=current.step if current else None,
        pending_request=services.runner.pending_request(run.id),
        message=message,
        merges=list(merges),
        rescan=RescanIn(enabled=run.rescan_enabled, max_tries=run.rescan_max_tries),
        rescans=[RescanOut.model_validate(r) for r in run.rescans or []],
        sem=_sem_out(run, session),
        patches=[_patch_out(p) for p in run.patches] if patches else None,
    )


def _sem_out(run: Run, session: Session) -> RunSemOut | None:
    """What placed the SEM image the run was drawn on (its calibration, when one did)."""
    if run.sem_id is None:
        return None
    record = (
        session.get(SemCalibrationRecord, run.sem_calibration_id)
        if run.sem_calibration_id is not None
        else None
    )
    if record is None:
        return RunSemOut(
            sem_id=run.sem_id,
            calibration_id=run.sem_calibration_id,
            rotation_deg=None,
            scale=None,
            residual_px=None,
        )
    found = calibration_out(record)
    return RunSemOut(
        sem_id=run.sem_id,
        calibration_id=record.id,
        rotation_deg=found.rotation_deg,
        scale=found.scale,
        residual_px=found.residual_px,
    )


def add_run(session: Session, services: Services, run: Run, what: str, operator: str) -> None:
    """Commit a new run (its HDF5 file named by its id) and announce it on the event stream."""
    session.add(run)
    session.flush()
    run.data_file = f"runs/run-{run.id:05d}.h5"  # under the data directory, wherever it is
    session.commit()
    services.events.emit(
        "run",
        f"run {run.id}: {what} ({operator})",
        run_id=run.id,
        data={"state": run.state, "actor": operator},
    )


def get_run(session: Session, run_id: int) -> Run:
    run = session.get(Run, run_id)
    if run is None:
        raise HTTPException(404, f"no run {run_id}: list them with GET /api/runs")
    return run


@contextmanager
def _started_by(session: Session, run_id: int, operator: str) -> Iterator[None]:
    """The run names ``operator`` as who started it, before the runner's events say it
    started (pages read the run then); named as before if the start is refused."""
    run = get_run(session, run_id)
    before, run.started_by = run.started_by, operator[:64]
    session.commit()
    try:
        yield
    except BaseException:
        session.expire_all()
        get_run(session, run_id).started_by = before
        session.commit()
        raise


def _current(run_id: int, services: Services, session: Session) -> RunOut:
    """The run as it is now, after the runner changed it from another session."""
    session.expire_all()
    return run_out(get_run(session, run_id), services, session, patches=False)


@router.post("/preview", response_model=PlanOut)
def preview(body: PlanIn, services: ServicesDep, session: SessionDep) -> PlanOut:
    """Plan a mosaic without creating a run (nothing moves)."""
    plan = _plan(body, services, session)
    return PlanOut(
        rows=plan.rows,
        cols=plan.cols,
        count=len(plan.patches),
        roi=RoiIn(x=plan.roi.x, y=plan.roi.y, width=plan.roi.width, height=plan.roi.height),
        extent=plan.extent,
        patches=[
            PatchOut(index=p.index, row=p.row, col=p.col, origin=p.origin, step="pending")
            for p in plan.patches
        ],
    )


@router.post("", status_code=201, response_model=RunOut)
def create_run(
    body: PlanIn, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> RunOut:
    """Plan a mosaic and create its run (state ``planned``); start it with ``/start``."""
    plan, sem = _plan_on(body, services, session)
    run = Run(
        state=RunState.PLANNED.value,
        roi_x=plan.roi.x,
        roi_y=plan.roi.y,
        roi_width=plan.roi.width,
        roi_height=plan.roi.height,
        patch_width=plan.patch.width,
        patch_height=plan.patch.height,
        pixels_x=plan.patch.pixels[0],
        pixels_y=plan.patch.pixels[1],
        overlap_x=plan.overlap[0],
        overlap_y=plan.overlap[1],
        rows=plan.rows,
        cols=plan.cols,
        line_rate=body.line_rate,
        rescan_enabled=body.rescan.enabled,
        rescan_max_tries=body.rescan.max_tries,
        rescans=[],
        instrument=services.microscope.description,
        message=f"planned by {operator}",
        created_by=operator[:64],
        data_file="",
        sem_id=sem.id if sem is not None else None,
        sem_calibration_id=sem.calibration_id if sem is not None else None,
    )
    run.patches = [
        PatchRecord(index=p.index, row=p.row, col=p.col, origin_x=p.origin[0], origin_y=p.origin[1])
        for p in plan.patches
    ]
    add_run(session, services, run, f"planned, {plan.rows} x {plan.cols} patches", operator)
    return run_out(run, services, session, patches=True)


@router.get("", response_model=list[RunOut])
def list_runs(services: ServicesDep, session: SessionDep) -> list[RunOut]:
    runs = session.scalars(select(Run).order_by(Run.id.desc())).all()
    return [run_out(r, services, session, patches=False) for r in runs]


@router.get("/{run_id}", response_model=RunOut)
async def read_run(run_id: RunId, services: ServicesDep) -> Response:
    """The run, its progress and its patches (served from memory until it changes)."""
    body, version = services.status.run(run_id)
    if body is None:
        body = await services.status.render(
            ("run", run_id, version), lambda: _render_run(run_id, services)
        )
        services.status.keep_run(run_id, version, body)
    return Response(body, media_type="application/json")


def _render_run(run_id: int, services: Services) -> bytes:
    with services.sessions() as session:
        out = run_out(get_run(session, run_id), services, session, patches=True)
    return out.model_dump_json().encode()


@router.post("/{run_id}/start", response_model=RunOut, status_code=202)
def start_run(
    run_id: RunId, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> RunOut:
    """Start a planned run, or resume a failed or interrupted one from its first patch
    not stored."""
    with _started_by(session, run_id, operator):
        services.runner.start(run_id, actor=operator)
    return _current(run_id, services, session)


@router.post("/{run_id}/pause", response_model=RunOut, status_code=202)
def pause_run(
    run_id: RunId, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> RunOut:
    """Ask a running run to pause; it does once the tip is off the surface."""
    get_run(session, run_id)
    services.runner.pause(run_id, actor=operator)
    return _current(run_id, services, session)


@router.post("/{run_id}/resume", response_model=RunOut, status_code=202)
def resume_run(
    run_id: RunId, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> RunOut:
    """Resume a paused run (or restart a failed or interrupted one)."""
    with _started_by(session, run_id, operator):
        services.runner.resume(run_id, actor=operator)
    return _current(run_id, services, session)


@router.post("/{run_id}/abort", response_model=RunOut)
def abort_run(
    run_id: RunId,
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
    body: Annotated[AbortIn | None, Body()] = None,
) -> RunOut:
    """Abort a run: an active one stops, retracts the tip and stops the axes (safe state).
    The answer comes once the run is aborted, or after :data:`ABORT_ANSWER` seconds at most
    with ``pending_request: "abort"`` while the tip is still being retracted (follow the run
    or its events to see it end)."""
    get_run(session, run_id)
    reason = (body.reason if body else "") or f"aborted by {operator}"
    services.runner.abort(run_id, actor=operator, reason=reason, wait=ABORT_ANSWER)
    return _current(run_id, services, session)


@router.post("/{run_id}/reset", response_model=RunOut)
def reset_run(
    run_id: RunId,
    body: ResetIn,
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
) -> RunOut:
    """After a fault (a crash, or a safe state not confirmed): the operator says what they
    checked (``note``; ``tip_changed`` when a new tip is mounted); the safe state is confirmed
    and the instrument released (run -> failed, resumable)."""
    get_run(session, run_id)
    services.runner.reset(
        run_id, actor=operator, note=body.note.strip(), tip_changed=body.tip_changed
    )
    return _current(run_id, services, session)


@router.get("/{run_id}/patches", response_model=list[PatchOut])
def list_patches(run_id: RunId, session: SessionDep) -> list[PatchOut]:
    return [_patch_out(p) for p in get_run(session, run_id).patches]


@router.get(
    "/{run_id}/patches/{index}/data",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "heights (ny, nx), metres, .npy"}},
)
def patch_data(run_id: RunId, index: PatchIndex, session: SessionDep) -> Response:
    """The stored heights of one patch as an ``.npy`` file (rows along y, metres)."""
    stored = _stored(session, run_id, index)
    response = npy_response(stored.heights, f"run{run_id}-patch{index:03d}.npy")
    response.headers["X-Origin"] = f"{stored.origin[0]!r},{stored.origin[1]!r}"
    response.headers["X-Pixel-Size"] = f"{stored.pixel_size[0]!r},{stored.pixel_size[1]!r}"
    return response


@router.get(
    "/{run_id}/patches/{index}/preview.png", response_class=Response, responses=PNG_RESPONSES
)
def patch_preview(
    run_id: RunId,
    index: PatchIndex,
    session: SessionDep,
    size: Annotated[int, Query(ge=16, le=1024, description="longer side, pixels")] = 96,
    bare: Annotated[bool, Query(description="the map alone, no title or bars")] = False,
) -> Response:
    """One stored patch as a picture (AFM colour map, nm colour bar, scale bar). ``bare``
    gives the map alone (a thumbnail); its height range, nm, is in ``X-Height-Range``."""
    stored = _stored(session, run_id, index)
    hmap = height_map(stored.heights, stored.origin, stored.pixel_size)
    if not bare:
        return png_response([(f"P{index}", hmap)], size=size)
    finite = stored.heights[np.isfinite(stored.heights)]
    lo, hi = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1e-9)
    shown = fit_size(stored.heights, size, pixel_size=stored.pixel_size)[::-1]  # +y up
    rgb = afm_colors((shown - lo) / max(hi - lo, 1e-12))
    return Response(
        encode_png(rgb),
        media_type="image/png",
        headers={"X-Height-Range": f"{lo * 1e9:.1f},{hi * 1e9:.1f}"},
    )


def _live(run_id: int, services: Services, session: Session) -> tuple[np.ndarray, dict[str, Any]]:
    """The run's live mosaic: the live merge's newest, or the one its end kept in its file."""
    run = get_run(session, run_id)
    live = services.runner.live
    held = live.mosaic(run_id) if live is not None else None
    if held is not None:
        return held
    try:
        return read_merge(run.file, LIVE_GROUP)
    except (KeyError, OSError):
        raise HTTPException(
            404,
            f"run {run_id} has no live mosaic yet: it appears once the run stores its first patch",
        ) from None


@router.get(
    "/{run_id}/live/mosaic.npy",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "live mosaic heights, metres"}},
)
def live_mosaic(run_id: RunId, services: ServicesDep, session: SessionDep) -> Response:
    """The live mosaic while the run scans (and after it ends): heights (ny, nx), metres, NaN
    where no patch covers; 404 before its first patch."""
    heights, _ = _live(run_id, services, session)
    return npy_response(heights, f"run{run_id}-live.npy")


@router.get("/{run_id}/live/mosaic.json")
def live_document(run_id: RunId, services: ServicesDep, session: SessionDep) -> dict[str, Any]:
    """The live mosaic's document (the result contract of docs/design.md: origin, pixel size,
    shape, every patch's transform) and ``patches_merged``, how many stored patches it holds."""
    _, document = _live(run_id, services, session)
    return document


@router.post("/{run_id}/patches/{index}/rescan", response_model=RunOut, status_code=202)
def rescan_patch(
    run_id: RunId,
    index: PatchIndex,
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
) -> RunOut:
    """Mark a stored patch of the active run for re-scan: it is scanned again next (whatever
    its tries), the scan it replaces kept aside in the run's file."""
    get_run(session, run_id)
    services.runner.request_rescan(run_id, index, actor=operator)
    return _current(run_id, services, session)


def _stored(session: Session, run_id: int, index: int) -> StoredPatch:
    run = get_run(session, run_id)
    patch = next((p for p in run.patches if p.index == index), None)
    if patch is None:
        raise HTTPException(
            404, f"run {run_id} has no patch {index}: indices are 0..{len(run.patches) - 1}"
        )
    if patch.step != "stored":
        raise HTTPException(404, f"patch {index} of run {run_id} is {patch.step}, not stored")
    return read_patch(run.file, index)


__all__ = ["PlanError", "add_run", "get_run", "router", "run_out"]
