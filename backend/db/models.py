"""SQLAlchemy 2 models. The schema is created and changed only by the Alembic migrations."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    DateTime,
    Dialect,
    Float,
    ForeignKey,
    Integer,
    String,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, object_session, relationship


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes in and out (SQLite stores them without their zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            raise ValueError("store aware datetimes (UTC)")
        return value.astimezone(UTC) if value is not None else None

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    pass


class Run(Base):
    """One mosaic: its plan, its state and where its data live."""

    __tablename__ = "runs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, onupdate=utcnow)
    state: Mapped[str] = mapped_column(String(16), index=True)
    roi_x: Mapped[float] = mapped_column(Float)
    roi_y: Mapped[float] = mapped_column(Float)
    roi_width: Mapped[float] = mapped_column(Float)
    roi_height: Mapped[float] = mapped_column(Float)
    patch_width: Mapped[float] = mapped_column(Float)
    patch_height: Mapped[float] = mapped_column(Float)
    pixels_x: Mapped[int] = mapped_column(Integer)
    pixels_y: Mapped[int] = mapped_column(Integer)
    overlap_x: Mapped[float] = mapped_column(Float)
    overlap_y: Mapped[float] = mapped_column(Float)
    rows: Mapped[int] = mapped_column(Integer)
    cols: Mapped[int] = mapped_column(Integer)
    line_rate: Mapped[float] = mapped_column(Float, default=2.0)
    instrument: Mapped[str] = mapped_column(String(512))
    current_patch: Mapped[int | None] = mapped_column(Integer, nullable=True)
    message: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    #: the run's HDF5 file, relative to the data directory (absolute in older databases)
    data_file: Mapped[str] = mapped_column(String(512))
    #: whether patches the quality gate fails are scanned again, and how often at most
    rescan_enabled: Mapped[bool] = mapped_column(Boolean, default=True)
    rescan_max_tries: Mapped[int] = mapped_column(Integer, default=2)
    #: every re-scan: ``{"index", "try", "reason"}``, in the order they were decided
    rescans: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)
    #: the SEM image its ROI was drawn on, and the SEM-to-stage calibration that placed that
    #: image (ids of ``sem_images`` and ``sem_calibrations``); None: not drawn on one, or
    #: placed by the image's own metadata or the nominal geometry
    sem_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    sem_calibration_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    #: who planned the run and who last started (or resumed) it: a user's name, or in the
    #: single-user mode the name the request gave (``X-Operator``)
    created_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    started_by: Mapped[str | None] = mapped_column(String(64), nullable=True)

    patches: Mapped[list[PatchRecord]] = relationship(
        back_populates="run", order_by="PatchRecord.index", cascade="all, delete-orphan"
    )

    @property
    def file(self) -> Path:
        """The run's file: ``data_file`` under the data directory its session was made for
        (so a data directory copied or restored elsewhere still finds its files)."""
        path = Path(self.data_file)
        if path.is_absolute():
            return path
        session = object_session(self)
        root = session.info.get("data_dir") if session is not None else None
        if root is None:
            raise RuntimeError(f"run {self.id}: no data directory to find {path} in")
        return Path(root) / path


class PatchRecord(Base):
    """One planned patch and its acquisition step; ``stored`` only once its data are on disk."""

    __tablename__ = "patches"
    __table_args__ = (UniqueConstraint("run_id", "index", name="uq_patch_run_index"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    index: Mapped[int] = mapped_column(Integer)
    row: Mapped[int] = mapped_column(Integer)
    col: Mapped[int] = mapped_column(Integer)
    origin_x: Mapped[float] = mapped_column(Float)
    origin_y: Mapped[float] = mapped_column(Float)
    step: Mapped[str] = mapped_column(String(16), default="pending")
    stored_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    dataset: Mapped[str | None] = mapped_column(String(128), nullable=True)
    #: the quality gate's word: ``ok``, ``rescanned`` (failed, scanned again), ``flagged``
    #: (failed every try: left out of the mosaic); None until judged
    quality: Mapped[str | None] = mapped_column(String(16), nullable=True)
    quality_reason: Mapped[str | None] = mapped_column(String(500), nullable=True)
    #: scans of this patch so far
    tries: Mapped[int] = mapped_column(Integer, default=0)

    run: Mapped[Run] = relationship(back_populates="patches")


class MergeJob(Base):
    """A merge of (some of) a run's patches, run in a worker process."""

    __tablename__ = "merge_jobs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    state: Mapped[str] = mapped_column(String(16), index=True)
    method: Mapped[str] = mapped_column(String(16))
    parameters: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    patch_ids: Mapped[list[int] | None] = mapped_column(JSON, nullable=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    residual: Mapped[float | None] = mapped_column(Float, nullable=True)
    message: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    result_group: Mapped[str | None] = mapped_column(String(128), nullable=True)
    #: who asked for the merge (``auto`` for the merge a finished run starts by itself)
    requested_by: Mapped[str | None] = mapped_column(String(64), nullable=True)


class Event(Base):
    """Everything that happened: state changes, progress, faults (the event stream's log)."""

    __tablename__ = "events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    run_id: Mapped[int | None] = mapped_column(
        ForeignKey("runs.id", ondelete="CASCADE"), nullable=True, index=True
    )
    kind: Mapped[str] = mapped_column(String(32), index=True)
    message: Mapped[str] = mapped_column(String(2000))
    data: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)


class SemImageRecord(Base):
    """An SEM image (file in the data dir) and its pixel-to-stage calibration."""

    __tablename__ = "sem_images"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    source: Mapped[str] = mapped_column(String(32))
    file: Mapped[str] = mapped_column(String(512))
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    origin_x: Mapped[float] = mapped_column(Float)
    origin_y: Mapped[float] = mapped_column(Float)
    pixel_x: Mapped[float] = mapped_column(Float)
    pixel_y: Mapped[float] = mapped_column(Float)
    #: the 2 x 2 pixel-to-stage map (metres per pixel step along columns, rows); None:
    #: diag(pixel_x, pixel_y), how images were placed before it was stored
    matrix: Mapped[list[list[float]] | None] = mapped_column(JSON, nullable=True)
    #: the scan rotation the SEM reported or the operator gave, degrees
    rotation: Mapped[float] = mapped_column(Float, default=0.0)
    #: where the SEM's own stage stood (x, y, z metres), when the image says
    sem_stage: Mapped[list[float] | None] = mapped_column(JSON, nullable=True)
    #: the SEM-to-stage calibration an acquired frame was placed through (None: none)
    calibration_id: Mapped[int | None] = mapped_column(Integer, nullable=True)


class SemCalibrationRecord(Base):
    """An SEM-to-stage calibration measured (:mod:`backend.sem_calibration`): the map of the
    reference image's pixels to the sample at the stage position it was taken at."""

    __tablename__ = "sem_calibrations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    instrument: Mapped[str] = mapped_column(String(512), index=True)
    field: Mapped[float] = mapped_column(Float)
    pixels: Mapped[int] = mapped_column(Integer)
    #: the scan rotation the SEM reported when it was measured, degrees
    scan_rotation: Mapped[float] = mapped_column(Float)
    matrix: Mapped[list[list[float]]] = mapped_column(JSON)
    offset: Mapped[list[float]] = mapped_column(JSON)
    stage: Mapped[list[float]] = mapped_column(JSON)
    residual_px: Mapped[float] = mapped_column(Float)
    sigma: Mapped[list[list[float]]] = mapped_column(JSON)
    #: every stage move made (metres) and the image shift it gave (pixels)
    moves: Mapped[list[list[float]]] = mapped_column(JSON)
    actor: Mapped[str] = mapped_column(String(100))


class SemRegistrationRecord(Base):
    """A merged mosaic registered onto an SEM image (:mod:`merge.correlative`):
    ``T_sem_mosaic`` maps a mosaic point (stage metres) to where the image shows it."""

    __tablename__ = "sem_registrations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    merge_id: Mapped[int] = mapped_column(Integer, index=True)
    sem_id: Mapped[int] = mapped_column(Integer)
    rotation_deg: Mapped[float] = mapped_column(Float)
    scale: Mapped[float] = mapped_column(Float)
    offset: Mapped[list[float]] = mapped_column(JSON)
    #: the general affine map ``[A | t]`` (2 x 3) when one was asked for
    affine: Mapped[list[list[float]] | None] = mapped_column(JSON, nullable=True)
    #: standard deviations: rotation_deg, scale, offset [x, y], centre (metres)
    sigma: Mapped[dict[str, Any]] = mapped_column(JSON)
    score: Mapped[float] = mapped_column(Float)
    rival: Mapped[float] = mapped_column(Float)
    overlap: Mapped[float] = mapped_column(Float)
    accepted: Mapped[bool] = mapped_column(Boolean)
    reason: Mapped[str | None] = mapped_column(String(500), nullable=True)
    #: the SE contrast's fitted weights (constant, tilt, slope x, slope y)
    weights: Mapped[list[float]] = mapped_column(JSON)
    #: the SEM-to-stage calibration that placed the SEM image, if one did
    calibration_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    actor: Mapped[str] = mapped_column(String(100))

    @property
    def transform(self) -> tuple[float, float, tuple[float, float]]:
        """``T_sem_mosaic`` as (rotation_deg, scale, offset), as ``Similarity`` takes it."""
        return self.rotation_deg, self.scale, (float(self.offset[0]), float(self.offset[1]))


class Calibration(Base):
    """A calibration of one axis or instrument quantity (e.g. a fine-mode gain)."""

    __tablename__ = "calibrations"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    axis: Mapped[str] = mapped_column(String(64), index=True)
    kind: Mapped[str] = mapped_column(String(64))
    value: Mapped[dict[str, Any]] = mapped_column(JSON)
