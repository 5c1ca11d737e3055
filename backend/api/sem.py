"""SEM images: acquire one from the instrument or upload a TIFF; the ROI is drawn on them."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, HTTPException, Response, UploadFile

from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.responses import NPY, PNG_RESPONSES, npy_response
from backend.api.schemas import SemAcquireIn, SemId, SemOut
from backend.db.models import SemImageRecord
from backend.sem_files import TiffError, pixel_map, read_sem_tiff, save_pixels, sem_path
from hardware.protocols import SEMImage
from merge.io.png import encode_png

router = APIRouter(prefix="/api/sem", tags=["sem"])


def stored_geometry(r: SemImageRecord, pixels: np.ndarray | None = None) -> SEMImage:
    """The stored image's geometry (and its pixels, when given) as the planner uses it."""
    matrix = None
    if r.matrix is not None:
        (a, b), (c, d) = r.matrix
        matrix = ((float(a), float(b)), (float(c), float(d)))
    return SEMImage(
        pixels if pixels is not None else np.zeros((1, 1)),
        (r.origin_x, r.origin_y),
        (r.pixel_x, r.pixel_y),
        matrix,
    )


def sem_out(r: SemImageRecord) -> SemOut:
    m = stored_geometry(r).map
    stage = r.sem_stage
    return SemOut(
        id=r.id,
        created_at=r.created_at,
        source=r.source,
        width=r.width,
        height=r.height,
        origin=(r.origin_x, r.origin_y),
        pixel_size=(r.pixel_x, r.pixel_y),
        matrix=((float(m[0, 0]), float(m[0, 1])), (float(m[1, 0]), float(m[1, 1]))),
        rotation_deg=r.rotation,
        sem_stage=(stage[0], stage[1], stage[2]) if stage is not None and len(stage) == 3 else None,
    )


def _store(
    session: SessionDep,
    services: ServicesDep,
    pixels: np.ndarray,
    *,
    source: str,
    geometry: SEMImage,
    rotation: float = 0.0,
    sem_stage: tuple[float, float, float] | None = None,
) -> SemImageRecord:
    """File first, then the row (no row without its file); the file is named by the row."""
    ny, nx = pixels.shape
    record = SemImageRecord(
        source=source,
        file="",
        width=nx,
        height=ny,
        origin_x=geometry.origin[0],
        origin_y=geometry.origin[1],
        pixel_x=geometry.pixel_size[0],
        pixel_y=geometry.pixel_size[1],
        matrix=[[float(v) for v in row] for row in geometry.map],
        rotation=rotation,
        sem_stage=list(sem_stage) if sem_stage is not None else None,
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
    """Take an SEM frame ``field`` metres across, ``pixels`` a side, ``dwell`` seconds a pixel,
    on ``detector``; placed with its field's centre at ``centre`` (stage, metres), turned by
    the scan rotation the SEM reports, rows down the screen."""
    sem = services.microscope.sem
    if sem is None:
        raise HTTPException(409, "this instrument has no SEM driver: upload a TIFF instead")
    try:
        frame = sem.acquire(
            field=body.field, pixels=body.pixels, dwell=body.dwell, detector=body.detector
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    size = (frame.pixel_size, frame.pixel_size)
    matrix = pixel_map(size, frame.rotation)
    middle = (body.pixels - 1) / 2
    origin = (
        body.centre[0] - (matrix[0][0] + matrix[0][1]) * middle,
        body.centre[1] - (matrix[1][0] + matrix[1][1]) * middle,
    )
    geometry = SEMImage(frame.pixels, origin, size, matrix)
    record = _store(
        session,
        services,
        frame.pixels,
        source=f"acquired ({frame.detector})",
        geometry=geometry,
        rotation=frame.rotation,
        sem_stage=frame.stage,
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
    rotation: Annotated[
        float | None,
        Form(
            ge=-360,
            le=360,
            description="scan rotation, degrees counter-clockwise, if the TIFF does not say",
        ),
    ] = None,
    origin_x: Annotated[
        float, Form(ge=-1, le=1, description="stage x of pixel (0, 0), metres")
    ] = 0.0,
    origin_y: Annotated[
        float, Form(ge=-1, le=1, description="stage y of pixel (0, 0), metres")
    ] = 0.0,
) -> SemOut:
    """Upload an SEM TIFF (row 0 the top line). Its pixel size, scan rotation and SEM stage
    position come from the vendor's tags (FEI/Thermo, ZEISS SmartSEM, TESCAN) when present,
    else the pixel size from ``pixel_size`` and the rotation from ``rotation`` (default 0);
    pixel (0, 0) lies at ``origin``. A plain route (run in a worker thread): decoding and
    storing never hold the event loop, so an abort is answered meanwhile."""
    limit = services.settings.max_upload_bytes
    data = file.file.read(limit + 1)
    if len(data) > limit:
        raise HTTPException(413, f"the file is larger than the {limit} byte upload limit")
    try:
        pixels, said = read_sem_tiff(data)
    except TiffError as exc:
        raise HTTPException(422, f"file: {exc}") from None
    size = said.pixel_size
    if size is not None and not all(1e-12 <= v <= 1e-4 for v in size):
        raise HTTPException(422, f"file: its {said.source} give a pixel size of {size} m")
    if size is None:
        if pixel_size is None:
            raise HTTPException(
                422,
                "pixel_size: the TIFF carries no SEM vendor pixel size; give pixel_size in "
                "metres per pixel",
            )
        size = (pixel_size, pixel_size)
    turned = said.rotation if said.rotation is not None else (rotation or 0.0)
    geometry = SEMImage(pixels, (origin_x, origin_y), size, pixel_map(size, turned))
    record = _store(
        session,
        services,
        pixels,
        source=f"upload ({said.source})",
        geometry=geometry,
        rotation=turned,
        sem_stage=said.stage,
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
