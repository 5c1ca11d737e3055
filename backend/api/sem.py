"""SEM images: acquire one from the instrument or upload a TIFF; the ROI is drawn on them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, HTTPException, Response, UploadFile

from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.responses import NPY, PNG_RESPONSES, npy_response
from backend.api.schemas import SemAcquireIn, SemId, SemOut
from backend.db.models import SemImageRecord
from backend.sem_files import TiffError, read_sem_tiff, save_pixels, sem_path
from merge.io.png import encode_png

router = APIRouter(prefix="/api/sem", tags=["sem"])


def sem_out(r: SemImageRecord) -> SemOut:
    return SemOut(
        id=r.id,
        created_at=r.created_at,
        source=r.source,
        width=r.width,
        height=r.height,
        origin=(r.origin_x, r.origin_y),
        pixel_size=(r.pixel_x, r.pixel_y),
    )


def _store(
    session: SessionDep,
    services: ServicesDep,
    pixels: np.ndarray,
    *,
    source: str,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
) -> SemImageRecord:
    """File first, then the row (no row without its file); the file is named by the row."""
    ny, nx = pixels.shape
    record = SemImageRecord(
        source=source,
        file="",
        width=nx,
        height=ny,
        origin_x=origin[0],
        origin_y=origin[1],
        pixel_x=pixel_size[0],
        pixel_y=pixel_size[1],
    )
    session.add(record)
    session.flush()
    path = sem_path(services.settings.data_dir, record.id)
    try:
        save_pixels(path, pixels)
    except OSError as exc:
        session.rollback()
        raise HTTPException(507, f"cannot store the SEM image: {exc}") from None
    record.file = str(path.resolve())
    session.commit()
    return record


@router.post("/acquire", status_code=201, response_model=SemOut)
def acquire(
    body: SemAcquireIn, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> SemOut:
    """Grab an SEM image centred on ``centre`` (stage, metres), ``field`` metres wide."""
    sem = services.microscope.sem
    if sem is None:
        raise HTTPException(409, "this instrument has no SEM driver: upload a TIFF instead")
    image = sem.grab(centre=body.centre, field=body.field, pixels=body.pixels)
    record = _store(
        session,
        services,
        image.pixels,
        source="acquired",
        origin=image.origin,
        pixel_size=image.pixel_size,
    )
    services.events.emit(
        "sem", f"SEM image {record.id} acquired ({operator})", data={"sem": record.id}
    )
    return sem_out(record)


@router.post("/upload", status_code=201, response_model=SemOut)
def upload(
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
    file: Annotated[UploadFile, File(description="a TIFF from the SEM")],
    pixel_size: Annotated[
        float | None,
        Form(gt=0, le=1e-4, description="metres per pixel, if the TIFF has no vendor tags"),
    ] = None,
    origin_x: Annotated[
        float, Form(ge=-1, le=1, description="stage x of pixel (0, 0), metres")
    ] = 0.0,
    origin_y: Annotated[
        float, Form(ge=-1, le=1, description="stage y of pixel (0, 0), metres")
    ] = 0.0,
) -> SemOut:
    """Upload an SEM TIFF. Its pixel size comes from the vendor's tags (FEI/Thermo, Zeiss)
    when present, else from ``pixel_size``. A plain route (run in a worker thread): decoding
    and storing never hold the event loop, so an abort is answered meanwhile."""
    limit = services.settings.max_upload_bytes
    data = file.file.read(limit + 1)
    if len(data) > limit:
        raise HTTPException(413, f"the file is larger than the {limit} byte upload limit")
    if not all(math.isfinite(v) for v in (origin_x, origin_y)):
        raise HTTPException(422, "origin_x and origin_y must be finite numbers of metres")
    try:
        pixels, vendor, source = read_sem_tiff(data)
    except TiffError as exc:
        raise HTTPException(422, f"file: {exc}") from None
    if vendor is None:
        if pixel_size is None or not math.isfinite(pixel_size):
            raise HTTPException(
                422,
                "pixel_size: the TIFF carries no SEM vendor pixel size; give pixel_size in "
                "metres per pixel",
            )
        vendor = (pixel_size, pixel_size)
    record = _store(
        session,
        services,
        pixels,
        source=f"upload ({source})",
        origin=(origin_x, origin_y),
        pixel_size=vendor,
    )
    services.events.emit(
        "sem", f"SEM image {record.id} uploaded ({operator})", data={"sem": record.id}
    )
    return sem_out(record)


@router.get("", response_model=list[SemOut])
def list_sem(session: SessionDep) -> list[SemOut]:
    return [sem_out(r) for r in session.query(SemImageRecord).order_by(SemImageRecord.id).all()]


def _record(session: SessionDep, sem_id: int) -> SemImageRecord:
    record = session.get(SemImageRecord, sem_id)
    if record is None:
        raise HTTPException(404, f"no SEM image {sem_id}: list them with GET /api/sem")
    return record


@router.get("/{sem_id}", response_model=SemOut)
def read_sem(sem_id: SemId, session: SessionDep) -> SemOut:
    return sem_out(_record(session, sem_id))


def _pixels(record: SemImageRecord) -> np.ndarray:
    try:
        pixels: np.ndarray = np.load(Path(record.file), allow_pickle=False)
    except OSError as exc:
        raise HTTPException(404, f"SEM image {record.id}: file not readable ({exc})") from None
    return pixels


@router.get("/{sem_id}/image.png", response_class=Response, responses=PNG_RESPONSES)
def sem_png(sem_id: SemId, session: SessionDep) -> Response:
    """The SEM image in grey levels (1-99 % stretched), full resolution, for drawing ROIs."""
    pixels = _pixels(_record(session, sem_id))
    lo, hi = np.percentile(pixels, [1, 99])
    grey = (np.clip((pixels - lo) / max(hi - lo, 1e-12), 0, 1) * 255 + 0.5).astype(np.uint8)
    return Response(encode_png(np.repeat(grey[..., None], 3, axis=-1)), media_type="image/png")


@router.get(
    "/{sem_id}/image.npy",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "grey levels (ny, nx)"}},
)
def sem_image(sem_id: SemId, session: SessionDep) -> Response:
    return npy_response(_pixels(_record(session, sem_id)), f"sem{sem_id}.npy")
