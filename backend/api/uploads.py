"""Offline runs: a folder of overlapping scans from any AFM, uploaded for a merge.

The files are kept as uploaded (in the data dir), read with :mod:`merge.io.formats`, and
stored as the patches of a run that had no acquisition: it is ``completed`` from the start,
listed and merged like any other, and its patches go to the 3D viewer as they are stored.
"""

from __future__ import annotations

import math
import shutil
import uuid
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, File, Form, HTTPException, UploadFile
from sqlalchemy.orm import Session

from backend.acquisition.state import RunState
from backend.api.deps import OperatorDep, ServicesDep, SessionDep
from backend.api.runs import add_run, run_out
from backend.api.schemas import RunOut
from backend.db.models import PatchRecord, Run
from backend.db.patch_store import dataset_name, mark_stored, write_patch
from backend.services import Services
from merge.io.formats import READABLE, AfmImage, FormatError, read_image, reader_for
from merge.io.formats.layout import LayoutError, scan_places

router = APIRouter(prefix="/api/runs", tags=["runs"])

MAX_FILES = 2500
#: Pixel sizes (metres) a scan may have, and how far from the stage's origin it may lie.
MIN_PIXEL, MAX_PIXEL = 1e-12, 1e-4
MAX_OFFSET = 1.0


def _places(
    images: list[AfmImage],
    names: list[str],
    rows: int | None,
    cols: int | None,
    overlap: tuple[float, float],
    order: str,
) -> list[tuple[tuple[float, float], int, int]]:
    """Where each file goes: its scan offset when no grid is given, else the grid."""
    grid = None
    if rows is not None or cols is not None:
        if rows is None or cols is None:
            raise HTTPException(422, "rows, cols: give both, or neither to use the scan offsets")
        grid = (rows, cols)
    try:
        places = scan_places(images, grid, overlap=overlap, order=order, names=names)
    except LayoutError as exc:
        raise HTTPException(422, f"rows, cols: {exc}") from None
    return [(o, r if r is not None else 0, c if c is not None else k)
            for k, (o, r, c) in enumerate(places)]  # fmt: skip


@router.post(
    "/offline",
    status_code=201,
    response_model=RunOut,
    form_limits={"max_files": MAX_FILES, "max_fields": 32},
)
def upload_patch_set(
    services: ServicesDep,
    session: SessionDep,
    operator: OperatorDep,
    files: Annotated[list[UploadFile], File(description=f"AFM files: {READABLE}")],
    rows: Annotated[int | None, Form(ge=1, le=1000)] = None,
    cols: Annotated[int | None, Form(ge=1, le=1000)] = None,
    overlap_x: Annotated[float, Form(ge=0, lt=0.9)] = 0.0,
    overlap_y: Annotated[float, Form(ge=0, lt=0.9)] = 0.0,
    order: Annotated[Literal["snake", "raster"], Form()] = "snake",
    pixel_size: Annotated[
        float | None, Form(gt=0, le=1e-4, description="metres, if files have none")
    ] = None,
    channel: Annotated[str | None, Form(max_length=100)] = None,
) -> RunOut:
    """Upload overlapping scans (in acquisition order) as a run with no acquisition, ready to
    merge. Positions come from the files' scan offsets, else from ``rows`` x ``cols`` with the
    overlaps, in snake or raster order."""
    if not 2 <= len(files) <= MAX_FILES:
        raise HTTPException(422, f"files: give 2 to {MAX_FILES} scans, got {len(files)}")
    if pixel_size is not None and not math.isfinite(pixel_size):
        raise HTTPException(422, "pixel_size must be a finite number of metres")
    folder = services.settings.data_dir / "uploads" / uuid.uuid4().hex
    folder.mkdir(parents=True)
    try:
        images, names = _receive(
            files, folder, services.settings.max_upload_bytes, channel, pixel_size
        )
        return _store(images, names, folder, services, session, operator,
                      rows, cols, (overlap_x, overlap_y), order)  # fmt: skip
    except BaseException:  # a refused (or failed) upload leaves nothing behind
        shutil.rmtree(folder, ignore_errors=True)
        raise


def _receive(
    files: list[UploadFile],
    folder: Path,
    limit: int,
    channel: str | None,
    pixel_size: float | None,
) -> tuple[list[AfmImage], list[str]]:
    """Save and read every upload; 413/422 for what cannot be (its name, never our path)."""
    used = 0
    images: list[AfmImage] = []
    names: list[str] = []
    for k, upload in enumerate(files):
        name = _short(Path(upload.filename or f"scan{k}").name)
        if reader_for(name) is None:
            raise HTTPException(422, f"files: {name}: unknown format; readable: {READABLE}")
        data = upload.file.read(limit - used + 1)
        used += len(data)
        if used > limit:
            raise HTTPException(413, f"the upload is larger than the {limit} byte limit")
        path = folder / f"{k:04d}-{name}"
        path.write_bytes(data)
        size = None if pixel_size is None else (pixel_size, pixel_size)
        try:
            images.append(read_image(path, channel=channel, pixel_size=size))
        except FormatError as exc:
            raise HTTPException(422, f"files: {str(exc).replace(str(path), name)}") from None
        names.append(name)
    return images, names


def _short(name: str, *, most: int = 120) -> str:
    """A file name kept to ``most`` characters (its suffix whole): what a file system takes."""
    if len(name) <= most:
        return name
    suffix = "".join(Path(name).suffixes)[-20:]
    return name[: most - len(suffix) - 1] + "~" + suffix


def _check_geometry(images: list[AfmImage], names: list[str]) -> None:
    """Refuse a file whose pixel size or offset is no place on a sample (422, by name)."""
    for image, name in zip(images, names, strict=True):
        if not all(MIN_PIXEL <= s <= MAX_PIXEL for s in image.pixel_size):
            raise HTTPException(
                422,
                f"files: {name}: pixel size {image.pixel_size[0]:.3g} x "
                f"{image.pixel_size[1]:.3g} m is outside {MIN_PIXEL:g}..{MAX_PIXEL:g} m: give "
                "pixel_size in metres",
            )
        if image.offset is not None and not all(abs(o) <= MAX_OFFSET for o in image.offset):
            raise HTTPException(
                422, f"files: {name}: its scan offset {image.offset} m is not on a sample stage"
            )


def _store(
    images: list[AfmImage],
    names: list[str],
    folder: Path,
    services: Services,
    session: Session,
    operator: str,
    rows: int | None,
    cols: int | None,
    overlap: tuple[float, float],
    order: str,
) -> RunOut:
    """The uploaded scans as a completed run: its rows, its file, its patches."""
    overlap_x, overlap_y = overlap
    _check_geometry(images, names)
    places = _places(images, names, rows, cols, (overlap_x, overlap_y), order)
    ny, nx = images[0].heights.shape
    width, height = nx * images[0].pixel_size[0], ny * images[0].pixel_size[1]
    xs = [o[0] for o, _, _ in places]
    ys = [o[1] for o, _, _ in places]
    run = Run(
        state=RunState.COMPLETED.value,
        roi_x=min(xs),
        roi_y=min(ys),
        roi_width=max(xs) + width - min(xs),
        roi_height=max(ys) + height - min(ys),
        patch_width=width,
        patch_height=height,
        pixels_x=nx,
        pixels_y=ny,
        overlap_x=overlap_x,
        overlap_y=overlap_y,
        rows=rows or 1,
        cols=cols or len(images),
        line_rate=1.0,
        instrument="offline upload",
        message=f"offline: {len(images)} uploaded scans ({operator})",
        data_file="",
    )
    run.patches = [
        PatchRecord(index=k, row=r, col=c, origin_x=o[0], origin_y=o[1])
        for k, (o, r, c) in enumerate(places)
    ]
    add_run(session, services, run, f"{len(images)} scans uploaded for an offline merge", operator)
    for k, (image, name, patch) in enumerate(zip(images, names, run.patches, strict=True)):
        write_patch(
            run.file,
            k,
            image.heights,
            origin=(patch.origin_x, patch.origin_y),
            pixel_size=image.pixel_size,
            line_times=np.zeros(image.heights.shape[0]),
            attrs={
                "source": name,
                "channel": image.channel,
                "upload": str(folder.relative_to(services.settings.data_dir)),
            },
        )
        mark_stored(session, patch, dataset_name(k))
        services.events.emit(
            "progress",
            f"run {run.id}: patch {k} stored ({k + 1}/{len(images)})",
            run_id=run.id,
            data={"stored": k + 1, "total": len(images), "patch": k},
        )
    if services.settings.auto_merge:
        services.merges.submit(run.id, method="default", parameters={}, patches=None)
    return run_out(run, services, session, patches=True)
