"""SEM images: acquire one from the instrument or upload a TIFF; the ROI is drawn on them."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, HTTPException, Query, Response, UploadFile
from sqlalchemy import select

from backend.acquisition.sem_stage import STEP, measure, place_frame, stage_position
from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.responses import NPY, PNG_RESPONSES, npy_response
from backend.api.schemas import (
    CalibrateIn,
    CalibrationOut,
    SemAcquireIn,
    SemId,
    SemOut,
    SemStateOut,
)
from backend.db.models import SemCalibrationRecord, SemImageRecord
from backend.sem_calibration import Calibration, CalibrationError
from backend.sem_files import TiffError, pixel_map, read_sem_tiff, save_pixels, sem_path
from hardware.errors import ProcedureError
from hardware.mcs_axis import TravelError
from hardware.nanonis.errors import NanonisError
from hardware.protocols import SEMImage
from hardware.sharksem.errors import SharkSEMError, SharkSEMTimeout
from hardware.smaract_errors import MCSError
from merge.io.png import encode_png

router = APIRouter(prefix="/api/sem", tags=["sem"])

#: What an instrument's link or procedure raises: the SEM's, the stage's, the controller's.
INSTRUMENT_ERRORS = (SharkSEMError, MCSError, NanonisError, ProcedureError)


def instrument_failed(exc: Exception, doing: str) -> HTTPException:
    """A 502 (504 for a time-out) saying what failed while ``doing``; nothing was stored."""
    code = 504 if isinstance(exc, SharkSEMTimeout) else 502
    return HTTPException(code, f"{doing} failed, nothing was stored: {exc}")


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
        calibration_id=r.calibration_id,
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
    calibration_id: int | None = None,
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
        calibration_id=calibration_id,
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
    on ``detector``; placed through the SEM-to-stage calibration in force, or without one
    with its field's centre at ``centre`` (stage, metres), turned by the scan rotation the SEM
    reports, rows down the screen."""
    sem = services.microscope.sem
    if sem is None:
        raise HTTPException(409, "this instrument has no SEM driver: upload a TIFF instead")
    try:
        frame = sem.acquire(
            field=body.field, pixels=body.pixels, dwell=body.dwell, detector=body.detector
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except INSTRUMENT_ERRORS as exc:
        raise instrument_failed(exc, "the SEM image") from None
    size = (frame.pixel_size, frame.pixel_size)
    record_in_force = _in_force(session, services, body.field)
    if record_in_force is not None:  # where the calibration says
        geometry = place_frame(
            frame,
            calibration=calibration_of(record_in_force),
            pixels_then=record_in_force.pixels,
            rotation_then=record_in_force.scan_rotation,
            stage_now=stage_position(services.microscope),
        )
    else:  # nominal: its field centred on ``centre``, turned by its scan rotation
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
        calibration_id=record_in_force.id if record_in_force is not None else None,
    )
    services.events.emit(
        "sem", f"SEM image {record.id} acquired ({operator})", data={"sem": record.id}
    )
    return sem_out(record)


#: A calibration serves frames whose field is within this factor of its own first (an SEM's
#: scale and rotation change a little with magnification); failing those, the newest.
NEAR_FIELD = 2.0


def _in_force(
    session: SessionDep, services: ServicesDep, field: float | None = None
) -> SemCalibrationRecord | None:
    """The calibration in force on this instrument: for frames of ``field``, the newest
    measured within :data:`NEAR_FIELD` of it, else the newest."""
    newest = (
        select(SemCalibrationRecord)
        .where(SemCalibrationRecord.instrument == services.microscope.description)
        .order_by(SemCalibrationRecord.id.desc())
        .limit(1)
    )
    if field is not None:
        near = session.scalars(
            newest.where(
                SemCalibrationRecord.field >= field / NEAR_FIELD,
                SemCalibrationRecord.field <= field * NEAR_FIELD,
            )
        ).first()
        if near is not None:
            return near
    return session.scalars(newest).first()


def calibration_of(r: SemCalibrationRecord) -> Calibration:
    return Calibration(
        np.asarray(r.matrix, dtype=np.float64),
        (r.offset[0], r.offset[1]),
        r.residual_px,
        np.asarray(r.sigma, dtype=np.float64),
        (r.stage[0], r.stage[1]),
        r.field,
    )


def calibration_record(
    c: Calibration,
    *,
    instrument: str,
    pixels: int,
    scan_rotation: float,
    moves: list[list[float]],
    actor: str,
) -> SemCalibrationRecord:
    """The row that stores calibration ``c`` (measured on frames of ``pixels`` at
    ``scan_rotation`` degrees, with its ``moves``; none when derived from another)."""
    if c.field is None:
        raise ValueError("a calibration is stored with the field of view it was measured at")
    return SemCalibrationRecord(
        instrument=instrument,
        field=c.field,
        pixels=pixels,
        scan_rotation=scan_rotation,
        matrix=c.matrix.tolist(),
        offset=list(c.offset),
        stage=list(c.stage),
        residual_px=c.residual_px,
        sigma=c.sigma.tolist(),
        moves=moves,
        actor=actor,
    )


def calibration_out(r: SemCalibrationRecord) -> CalibrationOut:
    c = calibration_of(r)
    m, sd = c.matrix, c.sigma
    middle = (r.pixels - 1) / 2
    centre = c.to_stage(middle, middle, at=(0.0, 0.0))
    return CalibrationOut(
        id=r.id,
        created_at=r.created_at,
        instrument=r.instrument,
        field=r.field,
        pixels=r.pixels,
        rotation_deg=c.rotation_deg,
        scale=c.scale,
        shear=c.shear,
        offset=centre,
        origin=c.offset,
        matrix=((m[0, 0], m[0, 1]), (m[1, 0], m[1, 1])),
        stage=c.stage,
        residual_px=r.residual_px,
        sigma=((sd[0, 0], sd[0, 1]), (sd[1, 0], sd[1, 1])),
        moves=[(a, b, c_, d) for a, b, c_, d in r.moves],
        actor=r.actor,
    )


@router.post("/calibrate", status_code=201, response_model=CalibrationOut)
def calibrate_sem(
    body: CalibrateIn, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> CalibrationOut:
    """Measure where the SEM's pixels lie on the stage: frames before and after known moves
    of the sample stage (the tip withdrawn, no run on the instrument; the stage ends where it
    began). Its offset comes from ``anchor`` (the tip seen in the reference frame), else from
    the SEM's nominal mounting over the tip's raster. A calibration that cannot be trusted is
    a 422 saying why; a busy instrument a 409."""
    m = services.microscope
    if m.sem is None:
        raise HTTPException(409, "this instrument has no SEM driver to calibrate")
    step = body.step if body.step is not None else body.field * STEP
    anchor = None
    if body.anchor is not None:
        a = body.anchor
        anchor = ((a.col, a.row), (a.x, a.y))
    try:
        with services.runner.exclusive("an SEM calibration"):
            found, rotation, moves = measure(
                m,
                field=body.field,
                pixels=body.pixels,
                step=step,
                dwell=body.dwell,
                detector=body.detector,
                anchor=anchor,
            )
    except CalibrationError as exc:
        raise HTTPException(422, f"calibration refused: {exc}") from None
    except TravelError as exc:
        raise HTTPException(
            422,
            f"step: a calibration move would leave the stage's travel ({exc}); give a "
            "smaller step or move the stage towards the middle of its travel first",
        ) from None
    except INSTRUMENT_ERRORS as exc:
        raise instrument_failed(exc, "the SEM calibration") from None
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from None
    record = calibration_record(
        found,
        instrument=m.description,
        pixels=body.pixels,
        scan_rotation=rotation,
        moves=moves,
        actor=operator,
    )
    session.add(record)
    session.commit()
    out = calibration_out(record)
    services.events.emit(
        "sem",
        f"SEM calibrated ({operator}): {out.rotation_deg:.3f}°, "
        f"{out.scale[0] * 1e9:.3f} x {out.scale[1] * 1e9:.3f} nm/px, "
        f"residual {out.residual_px:.2f} px",
        data={"calibration": record.id},
    )
    return out


@router.get("/calibration", response_model=CalibrationOut)
def calibration_in_force(
    services: ServicesDep,
    session: SessionDep,
    field: Annotated[
        float | None, Query(gt=0, le=1e-3, description="for frames of this field, metres")
    ] = None,
) -> CalibrationOut:
    """The SEM-to-stage calibration acquired frames are placed through: the newest, or for
    frames of ``field`` the newest measured within a factor of two of it (else the newest)."""
    record = _in_force(session, services, field)
    if record is None:
        raise HTTPException(404, "no SEM calibration yet: run POST /api/sem/calibrate")
    return calibration_out(record)


@router.get("/microscope", response_model=SemStateOut)
def microscope_state(services: ServicesDep) -> SemStateOut:
    """What the SEM reports now: its field of view, scan rotation and own stage."""
    sem = services.microscope.sem
    if sem is None:
        raise HTTPException(409, "this instrument has no SEM driver")
    try:
        field, rotation = sem.view_field(), sem.scan_rotation()
        x, y, z, turned, tilt = sem.stage_position()
    except INSTRUMENT_ERRORS as exc:
        raise instrument_failed(exc, "reading the SEM") from None
    return SemStateOut(
        field=field, scan_rotation_deg=rotation, stage=(x, y, z), stage_rotation_deg=turned,
        stage_tilt_deg=tilt,
    )  # fmt: skip


@router.get("/calibrations", response_model=list[CalibrationOut])
def calibrations(services: ServicesDep, session: SessionDep) -> list[CalibrationOut]:
    """This instrument's SEM calibrations, newest (the one in force) first."""
    records = session.scalars(
        select(SemCalibrationRecord)
        .where(SemCalibrationRecord.instrument == services.microscope.description)
        .order_by(SemCalibrationRecord.id.desc())
    ).all()
    return [calibration_out(r) for r in records]


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


def sem_pixels(record: SemImageRecord) -> np.ndarray:
    try:
        pixels: np.ndarray = np.load(Path(record.file), allow_pickle=False)
    except OSError as exc:
        raise HTTPException(404, f"SEM image {record.id}: file not readable ({exc})") from None
    return pixels


@router.get("/{sem_id}/image.png", response_class=Response, responses=PNG_RESPONSES)
def sem_png(sem_id: SemId, session: SessionDep) -> Response:
    """The SEM image in grey levels (1-99 % stretched), full resolution, for drawing ROIs."""
    pixels = sem_pixels(_record(session, sem_id))
    lo, hi = np.percentile(pixels, [1, 99])
    grey = (np.clip((pixels - lo) / max(hi - lo, 1e-12), 0, 1) * 255 + 0.5).astype(np.uint8)
    return Response(encode_png(np.repeat(grey[..., None], 3, axis=-1)), media_type="image/png")


@router.get(
    "/{sem_id}/image.npy",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "grey levels (ny, nx)"}},
)
def sem_image(sem_id: SemId, session: SessionDep) -> Response:
    return npy_response(sem_pixels(_record(session, sem_id)), f"sem{sem_id}.npy")
