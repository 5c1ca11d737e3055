"""Request and response bodies of the REST API (SI units: metres, seconds, hertz)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from fastapi import Path
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat, model_validator

#: Largest id or index accepted (the database's integers are 64-bit; JSON's exact to 2^53).
MAX_ID = 2**53
RunId = Annotated[int, Path(ge=1, le=MAX_ID, description="run id")]
JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="merge job id")]
SemId = Annotated[int, Path(ge=1, le=MAX_ID, description="SEM image id")]
PatchIndex = Annotated[int, Path(ge=0, le=MAX_ID, description="patch index (acquisition order)")]

Metres = Annotated[FiniteFloat, Field(description="metres")]
PositiveMetres = Annotated[FiniteFloat, Field(gt=0, description="metres")]


class Strict(BaseModel):
    """A request body that refuses fields it does not know (a typo is a 422, not ignored)."""

    model_config = ConfigDict(extra="forbid")


# -- requests ----------------------------------------------------------------------------------


class RoiIn(Strict):
    """Region of interest in the stage frame: lower-left corner and size, metres."""

    x: Metres
    y: Metres
    width: PositiveMetres
    height: PositiveMetres


class SemRoiIn(Strict):
    """Region of interest as a rectangle of pixels of a stored SEM image."""

    sem_id: int = Field(gt=0, le=MAX_ID)
    col: FiniteFloat = Field(ge=0, description="left column, pixels")
    row: FiniteFloat = Field(ge=0, description="top row, pixels")
    width: FiniteFloat = Field(gt=0, description="pixels")
    height: FiniteFloat = Field(gt=0, description="pixels")


class PatchIn(Strict):
    """One patch's scan range (metres) and pixels."""

    width: PositiveMetres
    height: PositiveMetres
    pixels: tuple[int, int] = Field(description="[nx, ny] pixels per patch")


class RescanIn(Strict):
    """Whether patches the quality gate fails are scanned again, and how often at most."""

    enabled: bool = True
    max_tries: int = Field(default=2, ge=1, le=10, description="scans of one patch at most")


class PlanIn(Strict):
    """A mosaic to plan: an ROI (stage metres, or SEM pixels), the patch and the overlaps."""

    roi: RoiIn | None = None
    sem_roi: SemRoiIn | None = None
    patch: PatchIn
    overlap: tuple[FiniteFloat, FiniteFloat] = Field(description="[ox, oy] fractions in [0, 0.9)")
    line_rate: FiniteFloat = Field(default=2.0, gt=0, le=50, description="scan lines per second")
    rescan: RescanIn = Field(default_factory=RescanIn)

    @model_validator(mode="after")
    def _one_roi(self) -> PlanIn:
        if (self.roi is None) == (self.sem_roi is None):
            raise ValueError("give exactly one of roi (stage metres) or sem_roi (SEM pixels)")
        return self


class ResetIn(Strict):
    """What the operator checked before releasing an instrument in fault."""

    note: str = Field(
        min_length=3,
        max_length=500,
        description="what was checked, for the record (e.g. 'tip inspected in the SEM: intact')",
    )
    tip_changed: bool = Field(default=False, description="a new tip was mounted")


class AbortIn(Strict):
    """Why a run is aborted (kept in its record and the audit trail)."""

    reason: str = Field(default="", max_length=500, description="why, for the record")


class MergeParams(Strict):
    """Merge options (see ``mosaic-afm merge --help``); omitted ones take their defaults."""

    cell: PositiveMetres | None = None
    max_iter: int | None = Field(default=None, ge=1, le=1000)
    max_shift: PositiveMetres | None = None
    coarse_cell: PositiveMetres | None = None
    init: Literal["auto", "nominal"] | None = None
    pixel_size: tuple[PositiveMetres, PositiveMetres] | None = None
    feather: FiniteFloat | None = Field(default=None, ge=0, le=0.5)
    self_calibrate: bool | None = Field(
        default=None,
        description="take out the scanner's row and column bend shared by every patch, measured "
        "from the overlaps (default method only); default: on for patches scanned without a "
        "position sensor (open-loop scan piezos)",
    )


class MergeIn(Strict):
    """A merge of a run's stored patches: the method, which patches, and its options."""

    method: Literal["default", "paper", "nominal", "zlevel"] = "default"
    patches: list[Annotated[int, Field(ge=0, le=MAX_ID)]] | None = Field(
        default=None, description="patch indices to merge; default every stored patch"
    )
    parameters: MergeParams = Field(default_factory=MergeParams)


class SemAcquireIn(Strict):
    """An SEM frame to take; ``centre`` is where its field's centre is taken to lie on the
    stage (its placement until the SEM-to-stage calibration says better)."""

    centre: tuple[Metres, Metres] = (0.0, 0.0)
    field: PositiveMetres = Field(default=24e-6, le=1e-2, description="image width, metres")
    pixels: int = Field(default=512, ge=8, le=4096)
    dwell: FiniteFloat = Field(default=1e-6, ge=1e-8, le=1e-3, description="s a pixel")
    detector: str = Field(default="SE", min_length=1, max_length=32)


class AnchorIn(Strict):
    """One point known in both frames: a pixel of the reference image (the tip seen there)
    and the sample position it shows (metres)."""

    col: FiniteFloat
    row: FiniteFloat
    x: Metres
    y: Metres


class CalibrateIn(Strict):
    """An SEM-to-stage calibration to run: frames of ``field`` metres, ``pixels`` a side,
    before and after stage moves of one to six ``step`` (default a twelfth of the field)
    along x and y both ways, and back at the start after each."""

    field: PositiveMetres = Field(default=20e-6, le=1e-3)
    pixels: int = Field(default=256, ge=64, le=2048)
    step: PositiveMetres | None = Field(default=None, le=1e-3)
    dwell: FiniteFloat = Field(default=1e-6, ge=1e-8, le=1e-3)
    detector: str = Field(default="SE", min_length=1, max_length=32)
    anchor: AnchorIn | None = None


class CalibrationOut(BaseModel):
    """The SEM-to-stage calibration: with the stage at ``s``, pixel ``(column, row)`` of a
    frame like its reference shows sample point ``offset - s + matrix @ ((column, row) - c)``,
    ``c`` the field's central pixel; equivalently ``origin + matrix @ (column, row)`` with the
    stage at ``stage``."""

    id: int
    created_at: datetime
    instrument: str
    field: float
    pixels: int
    rotation_deg: float = Field(description="of the image's columns from the stage's +x")
    scale: tuple[float, float] = Field(description="metres per pixel along columns, rows")
    shear: float = Field(description="cosine of the angle between the pixel axes")
    offset: tuple[float, float] = Field(
        description="where the field's centre lies in the stage's frame (metres): the sample "
        "point under it with the stage at 0"
    )
    origin: tuple[float, float] = Field(
        description="the sample point of pixel (0, 0) with the stage at ``stage`` (metres)"
    )
    matrix: tuple[tuple[float, float], tuple[float, float]]
    stage: tuple[float, float]
    residual_px: float
    sigma: tuple[tuple[float, float], tuple[float, float]]
    moves: list[tuple[float, float, float, float]] = Field(
        description="each stage move (m) and the image shift it gave (columns, rows)"
    )
    actor: str


LinkFault = Literal["silent", "garbage", "error", "drop"]
#: Faults that spoil the scans of chosen patches (:mod:`hardware.sim.faults`).
SpoilingFault = Literal["tip_change", "parachute", "lost_lines", "z_jump"]
SimFault = LinkFault | SpoilingFault | Literal["no_surface", "crash", "none"]


class SimFaultIn(Strict):
    """Make the simulated instrument misbehave (``none`` heals everything; ``crash`` lifts
    the sample under the scanning tip by a step no loop follows: the tip crashes).

    A link fault (``silent``, ``garbage``, ``error``, ``drop``) acts on the ``link``'s next
    ``count`` commands; a spoiling fault (``tip_change``, ``parachute``, ``lost_lines``,
    ``z_jump``) spoils the scans of the ``patches`` (indices) of the active or next run,
    ``count`` times each (default: every try)."""

    fault: SimFault
    link: Literal["stage", "robot"] = "robot"
    count: int | None = Field(
        default=None,
        ge=1,
        le=100000,
        description="commands (link faults) or scans per patch (spoiling faults) to misbehave "
        "on; default: until healed",
    )
    code: int = Field(default=150, ge=1, le=65535, description="controller error code to answer")
    patches: list[Annotated[int, Field(ge=0, le=MAX_ID)]] | None = Field(
        default=None, max_length=10000, description="patch indices a spoiling fault spoils"
    )

    @model_validator(mode="after")
    def _patches_for_spoiling(self) -> SimFaultIn:
        spoiling = self.fault in ("tip_change", "parachute", "lost_lines", "z_jump")
        if spoiling and not self.patches:
            raise ValueError(f"fault {self.fault!r} spoils chosen patches: give patches, e.g. [12]")
        if not spoiling and self.patches is not None:
            raise ValueError(f"fault {self.fault!r} acts on a link, not on patches: drop patches")
        return self


# -- responses ---------------------------------------------------------------------------------


class PatchOut(BaseModel):
    """One planned patch: its place in the grid, its origin on the stage (metres) and its step."""

    index: int
    row: int
    col: int
    origin: tuple[float, float]
    step: str
    stored_at: datetime | None = None
    quality: Literal["ok", "rescanned", "flagged"] | None = Field(
        default=None,
        description="the quality gate's word: ok, rescanned (failed, scanned again) or flagged "
        "(failed every try: left out of the mosaic); null until judged",
    )
    reason: str | None = Field(default=None, description="why it was re-scanned or flagged")
    tries: int = Field(default=0, description="scans of this patch so far")


class RescanOut(BaseModel):
    """One re-scan decided: the patch, the try it starts (2: the first re-scan) and why."""

    model_config = ConfigDict(validate_by_name=True, serialize_by_alias=True)

    index: int
    try_: int = Field(alias="try")
    reason: str


class ProgressOut(BaseModel):
    """Patches stored of the total planned."""

    stored: int
    total: int


class PlanOut(BaseModel):
    """A planned mosaic (nothing moved): its grid, ROI, extent and patches in snake order."""

    rows: int
    cols: int
    count: int
    roi: RoiIn
    extent: tuple[float, float, float, float] = Field(description="xmin, ymin, xmax, ymax")
    patches: list[PatchOut]


#: A stored number as an answer gives it: null where the row holds no finite number.
StoredFloat = float | None


class RoiOut(BaseModel):
    """The region of interest a run covers: lower-left corner and size, metres."""

    x: StoredFloat
    y: StoredFloat
    width: StoredFloat
    height: StoredFloat


class PatchShapeOut(BaseModel):
    """A run's patch: scan range (metres) and pixels."""

    width: StoredFloat
    height: StoredFloat
    pixels: tuple[int, int] = Field(description="[nx, ny] pixels per patch")


class RunSemOut(BaseModel):
    """The SEM image a run's ROI was drawn on, and what placed that image on the stage."""

    sem_id: int
    calibration_id: int | None = Field(
        description="the SEM-to-stage calibration that placed the image; None: the image's "
        "own metadata or the nominal geometry placed it"
    )
    rotation_deg: float | None = Field(description="the calibration's rotation, degrees")
    scale: tuple[float, float] | None = Field(description="its metres per pixel (columns, rows)")
    residual_px: float | None


class RunOut(BaseModel):
    """A run: its plan, state, progress, the step of its current patch, re-scans and merges."""

    id: int
    state: str
    created_at: datetime
    updated_at: datetime
    roi: RoiOut
    patch: PatchShapeOut
    overlap: tuple[StoredFloat, StoredFloat]
    line_rate: StoredFloat
    damage: list[str] = Field(
        default_factory=list,
        description="what of the stored row is not a usable number (such a run is listed, "
        "never merged or scanned)",
    )
    rows: int
    cols: int
    instrument: str
    progress: ProgressOut
    current_patch: int | None
    current_step: str | None
    pending_request: str | None = Field(description="pause or abort asked, not yet in effect")
    message: str | None
    created_by: str | None = Field(default=None, description="who planned the run")
    started_by: str | None = Field(default=None, description="who last started or resumed it")
    merges: list[int]
    rescan: RescanIn
    rescans: list[RescanOut] = Field(description="every re-scan decided: patch, try, reason")
    sem: RunSemOut | None = Field(
        default=None, description="the SEM image the ROI was drawn on (None: drawn in metres)"
    )
    patches: list[PatchOut] | None = None


class MergeOut(BaseModel):
    """A merge job: state, progress, residual, and where its mosaic is once done."""

    id: int
    run_id: int
    state: str
    method: str
    parameters: dict[str, Any]
    patches: list[int] | None
    progress: float
    iteration: int
    residual: float | None
    message: str | None
    created_at: datetime
    finished_at: datetime | None
    requested_by: str | None = Field(
        default=None, description="who asked for the merge ('auto': the run's own)"
    )
    mosaic_npy: str | None
    mosaic_json: str | None


class SemOut(BaseModel):
    """A stored SEM image and where its pixels lie on the stage (an affine map)."""

    id: int
    created_at: datetime
    source: str
    width: int
    height: int
    origin: tuple[float, float] = Field(description="stage position of pixel (0, 0), metres")
    pixel_size: tuple[float, float]
    matrix: tuple[tuple[float, float], tuple[float, float]] = Field(
        description="stage metres per pixel step: stage = origin + matrix @ (column, row)"
    )
    rotation_deg: float = Field(description="the image's scan rotation, degrees")
    sem_stage: tuple[float, float, float] | None = Field(
        default=None, description="where the SEM's own stage stood (x, y, z), metres"
    )
    calibration_id: int | None = Field(
        default=None, description="the SEM-to-stage calibration that placed it (None: none)"
    )


class SemStateOut(BaseModel):
    """What the SEM reports now."""

    field: float = Field(description="field of view across, metres")
    scan_rotation_deg: float
    stage: tuple[float, float, float] = Field(description="the SEM's own stage x, y, z, metres")
    stage_rotation_deg: float
    stage_tilt_deg: float


class InstrumentOut(BaseModel):
    """The instrument now: state, positions (metres), frequency shift (Hz), safe state."""

    description: str
    simulated: bool
    state: Literal["idle", "running", "fault", "error"]
    active_run: int | None
    safe_state: bool | None
    positions: dict[str, float | None] | None
    frequency_shift: float | None
    loop_engaged: bool | None
    fine_range: tuple[float, float]
    message: str | None = None


class ErrorOut(BaseModel):
    """Every error's answer: ``detail`` says what went wrong and what to fix."""

    detail: Any


class RegistrationIn(Strict):
    """Register a merge's mosaic onto a stored SEM image."""

    sem: int = Field(gt=0, le=MAX_ID, description="the SEM image's id (GET /api/sem)")
    affine: bool = Field(default=False, description="fit shear and two scales too")


class TransformOut(BaseModel):
    """``T_sem_mosaic``: ``p' = scale R(rotation) p + offset``, stage metres: where the SEM
    image (through its own pixel-to-stage map) shows the mosaic's point ``p``."""

    rotation_deg: float
    scale: float
    offset: tuple[float, float]


class RegistrationSigmaOut(BaseModel):
    """A registration's standard deviations."""

    rotation_deg: float
    scale: float
    offset: tuple[float, float] = Field(description="metres (about the stage's origin)")
    centre: float = Field(description="where the mosaic's centre lands, metres")


class CalibrationCheckOut(BaseModel):
    """How far the SEM-to-stage calibration that placed the image is off where the mosaic
    lies, against what it stated."""

    id: int
    displacement_px: float = Field(description="the registration's shift of the mosaic's centre")
    stated_px: float = Field(
        description="the calibration's expanded uncertainty there (coverage factor 2, about "
        "95 %), SEM pixels"
    )


class RegistrationOut(BaseModel):
    """A merged mosaic registered on an SEM image (``T_sem_mosaic``) and how sure."""

    id: int
    created_at: datetime
    merge_id: int
    sem_id: int
    transform: TransformOut
    affine: list[list[float]] | None
    sigma: RegistrationSigmaOut
    score: float = Field(description="correlation of the fitted SE contrast with the image")
    rival: float = Field(description="the best match elsewhere, over the best")
    overlap: float
    accepted: bool
    reason: str | None
    weights: list[float] = Field(description="SE contrast: constant, tilt, slope x, slope y")
    calibration: CalibrationCheckOut | None
    actor: str


class OverlayOut(BaseModel):
    """Where the overlay picture lies: its SEM pixels and the map from its pixels to the
    mosaic's coordinates (to draw a profile on it)."""

    registration_id: int
    sem_id: int
    box: tuple[int, int, int, int] = Field(
        description="the SEM image's pixels it shows: first column, first row, columns, rows"
    )
    pixel_to_mosaic: list[list[float]] = Field(
        description="2 x 3: mosaic (x, y) metres = M @ (column, row, 1) of the picture"
    )


class ProfileOut(BaseModel):
    """Heights and SEM signal along a segment of the mosaic (NaN as null where either does
    not reach)."""

    distance: list[float] = Field(description="along the segment, metres")
    height: list[float | None] = Field(description="metres")
    sem: list[float | None] = Field(description="the SEM's signal, its own units")
