"""Merge jobs: start one from a run, follow it, cancel it, download its mosaic."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Response
from fastapi.responses import JSONResponse
from sqlalchemy import select

from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.responses import NPY, PNG_RESPONSES, height_map, npy_response, png_response
from backend.api.runs import get_run
from backend.api.schemas import JobId, MergeIn, MergeOut, MergeParams, RunId
from backend.db.models import MergeJob, Run, SemRegistrationRecord
from backend.db.patch_store import read_merge, read_merge_document
from merge import MergeConfig
from merge.io.formats import export_heights

router = APIRouter(tags=["merges"])


def merge_out(job: MergeJob) -> MergeOut:
    done = job.state == "done"
    return MergeOut(
        id=job.id,
        run_id=job.run_id,
        state=job.state,
        method=job.method,
        parameters=job.parameters or {},
        patches=job.patch_ids,
        progress=job.progress,
        iteration=job.iteration,
        residual=job.residual,
        message=job.message,
        created_at=job.created_at,
        finished_at=job.finished_at,
        requested_by=job.requested_by,
        mosaic_npy=f"/api/merges/{job.id}/mosaic.npy" if done else None,
        mosaic_json=f"/api/merges/{job.id}/mosaic.json" if done else None,
    )


def _job(session: SessionDep, job_id: int) -> MergeJob:
    job = session.get(MergeJob, job_id)
    if job is None:
        raise HTTPException(404, f"no merge job {job_id}")
    return job


#: The finest a merge's pixel or cell may be, as a share of the scans' own pixel, and the
#: most pixels its mosaic may have (a quarter of the scans' pixel adds nothing but memory).
FINEST_SHARE = 0.25
MOST_PIXELS = 1 << 30


def _check_scale(run: Run, p: MergeParams) -> None:
    """Refuse a pixel or cell far finer than the scans' own, or a mosaic too large to hold,
    before a merge process is started for it (422 naming the parameter)."""
    scan = min(run.patch_width / run.pixels_x, run.patch_height / run.pixels_y)
    for name, value in (("pixel_size", min(p.pixel_size) if p.pixel_size else None),
                        ("cell", p.cell), ("coarse_cell", p.coarse_cell)):  # fmt: skip
        if value is not None and value < FINEST_SHARE * scan:
            raise HTTPException(
                422,
                f"parameters.{name}: {value * 1e9:.3g} nm is finer than a quarter of the scans' "
                f"own {scan * 1e9:.3g} nm pixel: it adds no detail, only memory",
            )
    if p.pixel_size is not None:
        px, py = p.pixel_size
        count = (run.roi_width / px + 1) * (run.roi_height / py + 1)
        if not count <= MOST_PIXELS:
            raise HTTPException(
                422,
                f"parameters.pixel_size: the mosaic would have {count:.3g} pixels, more than "
                f"{MOST_PIXELS}: use a larger pixel",
            )


@router.post("/api/runs/{run_id}/merges", status_code=202, response_model=MergeOut)
def start_merge(
    run_id: RunId, body: MergeIn, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> MergeOut:
    """Queue a merge of the run's stored patches (all, or the listed indices)."""
    _check_scale(get_run(session, run_id), body.parameters)
    parameters: dict[str, Any] = body.parameters.model_dump(exclude_none=True)
    if "pixel_size" in parameters:
        parameters["pixel_size"] = list(parameters["pixel_size"])
    try:
        p = body.parameters
        MergeConfig(
            method=body.method,
            cell=p.cell,
            max_iter=p.max_iter,
            max_shift=p.max_shift,
            coarse_cell=p.coarse_cell,
            init=p.init or "auto",
            pixel_size=p.pixel_size,
            feather=0.15 if p.feather is None else p.feather,
            self_calibrate=bool(p.self_calibrate),
        )
    except ValueError as exc:
        raise HTTPException(422, f"parameters: {exc}") from None
    job_id = services.merges.submit(
        run_id,
        method=body.method,
        parameters=parameters,
        patches=body.patches,
        requested_by=operator,
    )
    return merge_out(_job(session, job_id))


@router.get("/api/runs/{run_id}/merges", response_model=list[MergeOut])
def list_merges(run_id: RunId, session: SessionDep) -> list[MergeOut]:
    return [
        merge_out(j)
        for j in session.query(MergeJob).filter_by(run_id=get_run(session, run_id).id).all()
    ]


@router.get("/api/merges/{job_id}", response_model=MergeOut)
def read_merge_job(job_id: JobId, session: SessionDep) -> MergeOut:
    return merge_out(_job(session, job_id))


@router.post("/api/merges/{job_id}/cancel", response_model=MergeOut, status_code=202)
def cancel_merge(
    job_id: JobId, services: ServicesDep, session: SessionDep, _: OperatorDep
) -> MergeOut:
    _job(session, job_id)
    services.merges.cancel(job_id)
    session.expire_all()
    return merge_out(_job(session, job_id))


def _stored(session: SessionDep, job_id: int) -> tuple[Path, str]:
    """The file and group of a done merge's result (404 while it is not done)."""
    job = _job(session, job_id)
    if job.state != "done" or not job.result_group:
        raise HTTPException(
            404, f"merge {job_id} is {job.state}: its mosaic exists once it is done"
        )
    run = session.get(Run, job.run_id)
    if run is None:
        raise HTTPException(404, f"the run of merge {job_id} was deleted")
    return run.file, job.result_group


def merge_result(session: SessionDep, job_id: int) -> tuple[Any, dict[str, Any]]:
    """A done merge's mosaic and document (404 while it is not done, or not readable)."""
    path, group = _stored(session, job_id)
    try:
        return read_merge(path, group)
    except (KeyError, OSError) as exc:
        raise HTTPException(404, f"merge {job_id}: result not readable ({exc})") from None


def merge_document(session: SessionDep, job_id: int) -> dict[str, Any]:
    """A done merge's document alone: its grid without reading its mosaic."""
    path, group = _stored(session, job_id)
    try:
        return read_merge_document(path, group)
    except (KeyError, OSError) as exc:
        raise HTTPException(404, f"merge {job_id}: result not readable ({exc})") from None


@router.get(
    "/api/merges/{job_id}/mosaic.npy",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "mosaic heights, metres, .npy"}},
)
def mosaic_npy(job_id: JobId, session: SessionDep) -> Response:
    """The merged height map (``mosaic.npy`` of docs/design.md): metres, NaN where uncovered."""
    heights, _ = merge_result(session, job_id)
    return npy_response(heights, f"merge{job_id}-mosaic.npy")


def with_registration(session: SessionDep, job_id: int, document: dict[str, Any]) -> dict[str, Any]:
    """The result document with the merge's last accepted registration onto an SEM image
    (``sem_registration``: the SEM image, ``T_sem_mosaic``, its uncertainty and score)."""
    record = session.scalars(
        select(SemRegistrationRecord)
        .where(SemRegistrationRecord.merge_id == job_id)
        .where(SemRegistrationRecord.accepted.is_(True))
        .order_by(SemRegistrationRecord.id.desc())
        .limit(1)
    ).first()
    if record is None:
        return document
    registration = {
        "id": record.id,
        "sem_id": record.sem_id,
        "transform": {
            "rotation_deg": record.rotation_deg,
            "scale": record.scale,
            "offset": record.offset,
        },
        "affine": record.affine,
        "sigma": record.sigma,
        "score": record.score,
        "calibration_id": record.calibration_id,
    }
    return {**document, "sem_registration": registration}


@router.get("/api/merges/{job_id}/mosaic.json")
def mosaic_json(job_id: JobId, session: SessionDep) -> JSONResponse:
    """The result document (``mosaic.json`` of docs/design.md): grid, per-patch transforms and
    quality report, and the last accepted registration onto an SEM image."""
    _, document = merge_result(session, job_id)
    return JSONResponse(with_registration(session, job_id, document))


@router.get("/api/merges/{job_id}/preview.png", response_class=Response, responses=PNG_RESPONSES)
def mosaic_preview(
    job_id: JobId,
    session: SessionDep,
    size: Annotated[int, Query(ge=32, le=2048, description="longer side, pixels")] = 480,
) -> Response:
    """The merged mosaic as a picture, with a nm colour bar and a scale bar."""
    heights, doc = merge_result(session, job_id)
    origin = (float(doc["origin"][0]), float(doc["origin"][1]))
    pixel = (float(doc["pixel_size"][0]), float(doc["pixel_size"][1]))
    return png_response([("MERGED", height_map(heights, origin, pixel))], size=size)


EXPORT_TYPES = {
    "gwy": "application/x-gwyddion",
    "tif": "image/tiff",
    "png": "image/png",
    "ply": "application/octet-stream",
    "stl": "model/stl",
}


@router.get(
    "/api/merges/{job_id}/mosaic.{fmt}",
    response_class=Response,
    responses={200: {"content": {t: {} for t in EXPORT_TYPES.values()}}},
)
def mosaic_export(job_id: JobId, fmt: str, session: SessionDep) -> Response:
    """The merged mosaic as Gwyddion ``.gwy`` (with the uncovered-pixel mask and the merge's
    metadata), 32-bit float ``.tif``, ``.png`` with colour and scale bars, or a ``.ply`` /
    ``.stl`` surface (metres)."""
    if fmt not in EXPORT_TYPES:
        raise HTTPException(
            404,
            f"no export .{fmt}: use mosaic.npy, mosaic.json or mosaic.{{{','.join(EXPORT_TYPES)}}}",
        )
    heights, doc = merge_result(session, job_id)
    doc = with_registration(session, job_id, doc)
    origin = (float(doc["origin"][0]), float(doc["origin"][1]))
    pixel = (float(doc["pixel_size"][0]), float(doc["pixel_size"][1]))
    with tempfile.TemporaryDirectory() as tmp:
        path = export_heights(
            Path(tmp) / f"mosaic.{fmt}", heights, pixel_size=pixel, origin=origin, document=doc
        )
        body = path.read_bytes()
    return Response(
        body,
        media_type=EXPORT_TYPES[fmt],
        headers={"Content-Disposition": f'attachment; filename="merge{job_id}-mosaic.{fmt}"'},
    )
