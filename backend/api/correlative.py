"""A merge's mosaic on an SEM image: registered (:mod:`merge.correlative`), overlaid."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Response
from sqlalchemy import select

from backend.acquisition.sem_stage import adjusted
from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.merges import merge_document, merge_result, with_registration
from backend.api.responses import PNG_RESPONSES
from backend.api.schemas import (
    CalibrationCheckOut,
    CalibrationOut,
    JobId,
    OverlayOut,
    ProfileOut,
    RegistrationIn,
    RegistrationOut,
    RegistrationSigmaOut,
    TransformOut,
)
from backend.api.sem import calibration_of, calibration_out, calibration_record, stored_geometry
from backend.db.models import SemCalibrationRecord, SemImageRecord, SemRegistrationRecord
from backend.sem_files import sem_view
from merge.correlative import RegistrationError, SEMView, Similarity, register_to_sem
from merge.io.formats import export_heights
from merge.io.overlay import mosaic_corners, overlay_frame, overlay_rgb, profile, sem_on_mosaic
from merge.io.png import encode_png

router = APIRouter(tags=["sem registration"])

#: The coverage factor of the calibration's stated uncertainty (an expanded uncertainty, as
#: metrology states one: about 95 % of placements fall within it).
COVERAGE = 2.0
#: How far from the placement a calibrated SEM image is searched: rotation (degrees), scale,
#: and shift (SEM pixels, 0.3 µm at least).
CALIBRATED_SEARCH = (1.0, 0.02, 20)


def _view(record: SemImageRecord) -> SEMView:
    try:
        return sem_view(record)
    except OSError as exc:
        raise HTTPException(404, f"SEM image {record.id}: file not readable ({exc})") from None


def _grid(doc: dict[str, Any]) -> tuple[tuple[float, float], tuple[float, float]]:
    origin = (float(doc["origin"][0]), float(doc["origin"][1]))
    pixel = (float(doc["pixel_size"][0]), float(doc["pixel_size"][1]))
    return origin, pixel


def _check(
    record: SemRegistrationRecord, session: SessionDep, sem: SemImageRecord, middle: np.ndarray
) -> CalibrationCheckOut | None:
    """How far the calibration that placed the image is off at the mosaic's centre (from the
    image's stored geometry: its pixels are not read)."""
    if record.calibration_id is None:
        return None
    found = session.get(SemCalibrationRecord, record.calibration_id)
    if found is None:
        return None
    t = Similarity(*record.transform)
    image = stored_geometry(sem)
    pixel = math.sqrt(abs(float(np.linalg.det(image.map))))
    shift = float(np.hypot(*(t.apply(middle) - middle))) / pixel
    calibration = calibration_of(found)
    # its uncertainty there: the residual of its fit (the stage's own errors at the moves'
    # ends), and its matrix's uncertainty carried from the image's centre out to the
    # mosaic's, in this image's pixels, expanded by the coverage factor
    reference_pixel = found.field / found.pixels
    at = np.asarray(image.to_pixel(float(middle[0]), float(middle[1])))
    reach = float(np.hypot(*(at - (np.array([sem.width, sem.height]) - 1) / 2)))
    spread = float(np.sqrt(np.sum(np.asarray(calibration.sigma) ** 2))) / reference_pixel
    stated = COVERAGE * math.hypot(found.residual_px * reference_pixel / pixel, reach * spread)
    return CalibrationCheckOut(id=found.id, displacement_px=shift, stated_px=stated)


def registration_out(
    record: SemRegistrationRecord, session: SessionDep, sem: SemImageRecord, middle: np.ndarray
) -> RegistrationOut:
    sigma = record.sigma
    return RegistrationOut(
        id=record.id,
        created_at=record.created_at,
        merge_id=record.merge_id,
        sem_id=record.sem_id,
        transform=TransformOut(
            rotation_deg=record.rotation_deg,
            scale=record.scale,
            offset=(record.offset[0], record.offset[1]),
        ),
        affine=record.affine,
        sigma=RegistrationSigmaOut(
            rotation_deg=sigma["rotation_deg"],
            scale=sigma["scale"],
            offset=(sigma["offset"][0], sigma["offset"][1]),
            centre=sigma["centre"],
        ),
        score=record.score,
        rival=record.rival,
        overlap=record.overlap,
        accepted=record.accepted,
        reason=record.reason,
        weights=list(record.weights),
        calibration=_check(record, session, sem, middle),
        actor=record.actor,
    )


def _middle(doc: dict[str, Any]) -> np.ndarray:
    """The mosaic's centre (stage metres), from its document's grid."""
    origin, pixel = _grid(doc)
    ny, nx = (int(v) for v in doc["shape"])
    out: np.ndarray = np.asarray(origin) + np.array([nx - 1, ny - 1]) * np.asarray(pixel) / 2
    return out


def _grid_document(session: SessionDep, job_id: int) -> dict[str, Any]:
    """A done merge's document with its mosaic's shape, its mosaic read only when a document
    of an older merge does not say it."""
    doc = merge_document(session, job_id)
    if "shape" not in doc:
        heights, doc = merge_result(session, job_id)
        doc = {**doc, "shape": list(heights.shape)}
    return doc


def _sem_record(session: SessionDep, sem_id: int) -> SemImageRecord:
    record = session.get(SemImageRecord, sem_id)
    if record is None:
        raise HTTPException(404, f"sem: no SEM image {sem_id}: list them with GET /api/sem")
    return record


def _finite(value: float) -> float:
    return value if math.isfinite(value) else -1.0


@router.post(
    "/api/merges/{job_id}/sem-registration", status_code=201, response_model=RegistrationOut
)
def register(
    job_id: JobId,
    body: RegistrationIn,
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
) -> RegistrationOut:
    """Register the merge's mosaic onto SEM image ``sem``: where the image shows the mosaic
    (``transform``), how sure, and whether the match can be trusted (``accepted``, else the
    ``reason``). A plain route: the search runs in a worker thread, never on the event loop."""
    heights, doc = merge_result(session, job_id)
    sem = _sem_record(session, body.sem)
    view = _view(sem)
    origin, pixel = _grid(doc)
    rotation, scale, shift = 5.0, 0.05, None  # the defaults: a nominally placed image
    if sem.calibration_id is not None:  # placed through a calibration: look near it
        rotation, scale, shift_px = CALIBRATED_SEARCH
        shift = max(shift_px * view.pixel, 0.3e-6)
    try:
        found = register_to_sem(
            heights,
            view,
            origin=origin,
            pixel_size=pixel,
            affine=body.affine,
            search_rotation=rotation,
            search_scale=scale,
            search_shift=shift,
        )
    except RegistrationError as exc:
        raise HTTPException(422, f"sem: {exc}") from None
    t = found.transform
    record = SemRegistrationRecord(
        merge_id=job_id,
        sem_id=sem.id,
        rotation_deg=t.rotation_deg,
        scale=t.scale,
        offset=[t.offset[0], t.offset[1]],
        affine=found.affine.tolist() if found.affine is not None else None,
        sigma={
            "rotation_deg": _finite(found.sigma_rotation_deg),
            "scale": _finite(found.sigma_scale),
            "offset": [_finite(v) for v in found.sigma_offset],
            "centre": _finite(found.sigma_here),
        },
        score=found.score,
        rival=found.rival,
        overlap=found.overlap,
        accepted=found.accepted,
        reason=found.reason,
        weights=list(found.weights),
        calibration_id=sem.calibration_id,
        actor=operator,
    )
    session.add(record)
    session.commit()
    said = "registered" if found.accepted else f"not registered ({found.reason})"
    services.events.emit(
        "sem",
        f"merge {job_id} {said} onto SEM image {sem.id} ({operator}): {t.rotation_deg:.3f}°, "
        f"scale {t.scale:.4f}, score {found.score:.2f}",
        data={"registration": record.id, "merge": job_id, "accepted": found.accepted},
    )
    return registration_out(record, session, sem, _middle({**doc, "shape": list(heights.shape)}))


def _last(session: SessionDep, job_id: int, *, accepted: bool = False) -> SemRegistrationRecord:
    query = select(SemRegistrationRecord).where(SemRegistrationRecord.merge_id == job_id)
    if accepted:
        query = query.where(SemRegistrationRecord.accepted.is_(True))
    record = session.scalars(query.order_by(SemRegistrationRecord.id.desc()).limit(1)).first()
    if record is None:
        what = "accepted registration" if accepted else "registration"
        raise HTTPException(
            404,
            f"merge {job_id} has no {what} onto an SEM image: POST "
            f'/api/merges/{job_id}/sem-registration with {{"sem": <id>}}',
        )
    return record


@router.get("/api/merges/{job_id}/sem-registration", response_model=RegistrationOut)
def last_registration(job_id: JobId, session: SessionDep) -> RegistrationOut:
    """The merge's last registration onto an SEM image."""
    record = _last(session, job_id)
    doc = _grid_document(session, job_id)
    return registration_out(record, session, _sem_record(session, record.sem_id), _middle(doc))


@router.get("/api/merges/{job_id}/sem-registrations", response_model=list[RegistrationOut])
def registrations(job_id: JobId, session: SessionDep) -> list[RegistrationOut]:
    """Every registration of the merge onto an SEM image, the last first."""
    records = session.scalars(
        select(SemRegistrationRecord)
        .where(SemRegistrationRecord.merge_id == job_id)
        .order_by(SemRegistrationRecord.id.desc())
    ).all()
    middle = _middle(_grid_document(session, job_id))  # not there, or not done: its 404
    return [registration_out(r, session, _sem_record(session, r.sem_id), middle) for r in records]


@router.get(
    "/api/merges/{job_id}/sem-overlay.png", response_class=Response, responses=PNG_RESPONSES
)
def sem_overlay(
    job_id: JobId,
    session: SessionDep,
    opacity: Annotated[float, Query(ge=0, le=1, description="0: the SEM, 1: the heights")] = 0.5,
) -> Response:
    """The mosaic in the AFM colours over the SEM image it was last registered on (an
    accepted registration), at the SEM's own pixels around it."""
    record = _last(session, job_id, accepted=True)
    heights, doc = merge_result(session, job_id)
    origin, pixel = _grid(doc)
    view = _view(_sem_record(session, record.sem_id))
    t = Similarity(*record.transform)
    try:
        rgb = overlay_rgb(
            heights, view, origin=origin, pixel_size=pixel, transform=t, opacity=opacity
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return Response(encode_png(rgb), media_type="image/png")


@router.get("/api/merges/{job_id}/sem-overlay", response_model=OverlayOut)
def sem_overlay_frame(job_id: JobId, session: SessionDep) -> OverlayOut:
    """Where :func:`sem_overlay`'s picture lies: its SEM pixels, and the map from its pixels
    to the mosaic's coordinates (a profile drawn on the picture is asked in those)."""
    record = _last(session, job_id, accepted=True)
    doc = _grid_document(session, job_id)
    origin, pixel = _grid(doc)
    ny, nx = (int(v) for v in doc["shape"])
    view = _view(_sem_record(session, record.sem_id))
    try:
        box, frame = overlay_frame(
            view, mosaic_corners((ny, nx), origin, pixel), Similarity(*record.transform)
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return OverlayOut(
        registration_id=record.id,
        sem_id=record.sem_id,
        box=box,
        pixel_to_mosaic=frame.tolist(),
    )


@router.post(
    "/api/merges/{job_id}/sem-registration/apply", status_code=201, response_model=CalibrationOut
)
def apply_registration(
    job_id: JobId, services: ServicesDep, session: SessionDep, operator: OperatorDep
) -> CalibrationOut:
    """Correct the SEM-to-stage calibration that placed the registered image by what the
    merge's last accepted registration measured there: a new calibration, in force from now
    on (the old one kept), logged."""
    record = _last(session, job_id, accepted=True)
    sem = _sem_record(session, record.sem_id)
    found = (
        session.get(SemCalibrationRecord, sem.calibration_id)
        if sem.calibration_id is not None
        else None
    )
    if found is None:
        raise HTTPException(
            409,
            f"SEM image {sem.id} was not placed through a calibration (its own metadata or "
            "its nominal pixel placed it): calibrate the SEM first (POST /api/sem/calibrate)",
        )
    t = Similarity(*record.transform)
    image = stored_geometry(sem)
    better = adjusted(
        calibration_of(found),
        pixels_then=found.pixels,
        image_origin=image.origin,
        image_matrix=np.asarray(image.map),
        image_pixels=sem.width,
        t_matrix=t.matrix,
        t_offset=t.offset,
    )
    new = calibration_record(
        better,
        instrument=found.instrument,
        pixels=found.pixels,
        scan_rotation=found.scan_rotation,
        moves=[],  # none made: adjusted from a registration
        actor=operator,
    )
    session.add(new)
    session.commit()
    out = calibration_out(new)
    services.events.emit(
        "sem",
        f"SEM calibration {found.id} adjusted by merge {job_id}'s registration {record.id} "
        f"({operator}): now calibration {new.id}, {out.rotation_deg:.3f}°",
        data={"calibration": new.id, "from": found.id, "registration": record.id},
    )
    return out


@router.get(
    "/api/merges/{job_id}/mosaic-sem.{fmt}",
    response_class=Response,
    responses={200: {"content": {t: {} for t in ("application/x-gwyddion", "image/tiff")}}},
)
def mosaic_with_sem(job_id: JobId, fmt: str, session: SessionDep) -> Response:
    """The merged mosaic with the SEM image it was last registered on, resampled on the
    mosaic's grid: a ``.gwy`` of two channels (heights, SEM signal) or a two-page ``.tif``;
    the registration in the file's metadata (``.gwy``)."""
    types = {"gwy": "application/x-gwyddion", "tif": "image/tiff"}
    if fmt not in types:
        raise HTTPException(404, f"no export mosaic-sem.{fmt}: use mosaic-sem.gwy or .tif")
    record = _last(session, job_id, accepted=True)
    heights, doc = merge_result(session, job_id)
    doc = with_registration(session, job_id, doc)
    origin, pixel = _grid(doc)
    view = _view(_sem_record(session, record.sem_id))
    t = Similarity(*record.transform)
    signal = sem_on_mosaic(view, heights.shape, origin=origin, pixel_size=pixel, transform=t)
    with tempfile.TemporaryDirectory() as tmp:
        path = export_heights(
            Path(tmp) / f"mosaic.{fmt}",
            heights,
            pixel_size=pixel,
            origin=origin,
            document=doc,
            channels=[(f"SEM image {record.sem_id}", signal, "")],
        )
        body = path.read_bytes()
    return Response(
        body,
        media_type=types[fmt],
        headers={"Content-Disposition": f'attachment; filename="merge{job_id}-mosaic-sem.{fmt}"'},
    )


@router.get("/api/merges/{job_id}/sem-profile", response_model=ProfileOut)
def sem_profile(
    job_id: JobId,
    session: SessionDep,
    x0: Annotated[float, Query(ge=-1, le=1, description="start x, metres (mosaic)")],
    y0: Annotated[float, Query(ge=-1, le=1, description="start y, metres")],
    x1: Annotated[float, Query(ge=-1, le=1, description="end x, metres")],
    y1: Annotated[float, Query(ge=-1, le=1, description="end y, metres")],
    samples: Annotated[int, Query(ge=2, le=4096)] = 256,
) -> ProfileOut:
    """The heights and the SEM signal along a segment drawn across the mosaic, the SEM read
    where the merge's last accepted registration puts it."""
    record = _last(session, job_id, accepted=True)
    heights, doc = merge_result(session, job_id)
    origin, pixel = _grid(doc)
    view = _view(_sem_record(session, record.sem_id))
    try:
        distance, height, signal = profile(
            heights,
            view,
            (x0, y0),
            (x1, y1),
            origin=origin,
            pixel_size=pixel,
            transform=Similarity(*record.transform),
            samples=samples,
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None

    def listed(values: np.ndarray) -> list[float | None]:
        return [float(v) if np.isfinite(v) else None for v in values]

    return ProfileOut(distance=distance.tolist(), height=listed(height), sem=listed(signal))
