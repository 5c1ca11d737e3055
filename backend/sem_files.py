"""SEM images in the data dir, and the pixel size a vendor wrote into a TIFF."""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from backend.db.models import SemImageRecord
from merge.correlative import SEMView
from merge.io.formats.image import FormatError
from merge.io.formats.tiff import check_declared

FloatArray = NDArray[np.float64]

_UNITS = {"m": 1.0, "mm": 1e-3, "µm": 1e-6, "um": 1e-6, "nm": 1e-9, "pm": 1e-12}


#: Values an SEM TIFF may declare (RGB counts three a pixel): 32 Mi, an SEM's largest usual
#: grey frame (8192 x 4096); a larger image is binned before upload.
MAX_SEM_VALUES = 1 << 25


class TiffError(ValueError):
    """The upload is not a usable TIFF image; the message says why."""


@dataclass(frozen=True)
class SemGeometry:
    """What an SEM file says of where its pixels are: the pixel size (metres, along columns
    and rows), the scan rotation (degrees, counter-clockwise) and the SEM stage's position
    (x, y, z metres); each None where the file does not say; ``source``, whose tags."""

    pixel_size: tuple[float, float] | None = None
    rotation: float | None = None
    stage: tuple[float, float, float] | None = None
    source: str = "request"


def _number(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def _pair(px: float | None, py: float | None) -> tuple[float, float] | None:
    """A pixel size from its two sides (one given: square), None unless positive."""
    if px is None or not px > 0:
        return None
    return (px, py) if py is not None and py > 0 else (px, px)


def _xyz(values: list[float | None]) -> tuple[float, float, float] | None:
    x, y, z = values
    return None if x is None or y is None or z is None else (x, y, z)


def _fei(meta: dict[str, Any]) -> SemGeometry:
    """Thermo Fisher / FEI: ``[Scan]`` PixelWidth and PixelHeight (m), ``[Beam]``
    ScanRotation (radians), ``[Stage]`` StageX, StageY, StageZ (m)."""
    scan = meta.get("Scan") or meta.get("EScan") or {}
    beam = meta.get("Beam") or {}
    stage = meta.get("Stage") or {}
    rotation = _number(beam.get("ScanRotation"))
    return SemGeometry(
        _pair(_number(scan.get("PixelWidth")), _number(scan.get("PixelHeight"))),
        math.degrees(rotation) if rotation is not None else None,
        _xyz([_number(stage.get(k)) for k in ("StageX", "StageY", "StageZ")]),
        "FEI/Thermo TIFF tags",
    )


def _zeiss_value(meta: dict[str, Any], key: str, unit: str | None = None) -> float | None:
    """A SmartSEM entry ``(label, value, unit)`` in SI (lengths in metres)."""
    entry = meta.get(key)
    if not entry or len(entry) < 2:
        return None
    value = _number(entry[1])
    if value is None:
        return None
    if unit == "length":
        scale = _UNITS.get(entry[2] if len(entry) > 2 else "nm")
        return None if scale is None else value * scale
    return value


def _zeiss(meta: dict[str, Any]) -> SemGeometry:
    """ZEISS SmartSEM: ``ap_image_pixel_size``, ``ap_scanrotation`` (degrees) and
    ``ap_stage_at_x``/``_y``/``_z``."""
    size = _zeiss_value(meta, "ap_image_pixel_size", "length") or _zeiss_value(
        meta, "ap_pixel_size", "length"
    )
    return SemGeometry(
        _pair(size, size),
        _zeiss_value(meta, "ap_scanrotation"),
        _xyz([_zeiss_value(meta, f"ap_stage_at_{a}", "length") for a in "xyz"]),
        "Zeiss TIFF tags",
    )


#: The TIFF tag TESCAN writes its header to (text of ``key=value`` lines).
TESCAN_TAG = 50431


def _tescan(text: str) -> SemGeometry:
    """TESCAN: its header's PixelSizeX, PixelSizeY (m), ScanRotation (degrees), StageX,
    StageY, StageZ (m)."""
    values: dict[str, float | None] = {}
    for line in text.splitlines():
        key, _, value = line.partition("=")
        values[key.strip()] = _number(value.strip())
    return SemGeometry(
        _pair(values.get("PixelSizeX"), values.get("PixelSizeY")),
        values.get("ScanRotation"),
        _xyz([values.get(k) for k in ("StageX", "StageY", "StageZ")]),
        "TESCAN TIFF header",
    )


def _geometry(tif: tifffile.TiffFile) -> SemGeometry:
    if tif.is_fei and tif.fei_metadata:
        return _fei(tif.fei_metadata)
    if tif.is_sem and tif.sem_metadata:
        return _zeiss(tif.sem_metadata)
    tag = tif.pages.first.tags.get(TESCAN_TAG)
    if tag is not None:
        value = tag.value
        text = value.decode("latin-1") if isinstance(value, bytes) else str(value)
        return _tescan(text)
    return SemGeometry()


def read_sem_tiff(data: bytes) -> tuple[FloatArray, SemGeometry]:
    """Grey levels (ny, nx, row 0 the top line) and what the vendor's tags say of where its
    pixels are (:class:`SemGeometry`: FEI/Thermo, ZEISS SmartSEM, TESCAN). A page declaring
    more than :data:`MAX_SEM_VALUES` values is refused from its header, before anything is
    decoded."""
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages.first
            check_declared(page, "the TIFF", limit=MAX_SEM_VALUES)
            pixels = np.asarray(page.asarray(), dtype=np.float32)
            geometry = _geometry(tif)
    except FormatError as exc:
        raise TiffError(str(exc)) from None
    except Exception as exc:  # tifffile raises many kinds on a bad file
        raise TiffError(f"not a readable TIFF image ({type(exc).__name__}: {exc})") from None
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4):
        pixels = pixels[..., :3].mean(axis=-1, dtype=np.float32)  # RGB(A) export: grey levels
    if pixels.ndim != 2 or min(pixels.shape) < 8:
        raise TiffError(f"need a 2-D grey image of at least 8 x 8 pixels, got {pixels.shape}")
    return pixels.astype(np.float64), geometry


def pixel_map(
    pixel_size: tuple[float, float], rotation: float
) -> tuple[tuple[float, float], tuple[float, float]]:
    """The pixel-to-stage matrix of an SEM image whose rows go down the screen, scanned
    turned by ``rotation`` degrees: ``R(rotation) @ diag(dx, -dy)``."""
    a = math.radians(rotation)
    c, s = math.cos(a), math.sin(a)
    dx, dy = pixel_size
    return ((c * dx, s * dy), (s * dx, -c * dy))


def sem_path(data_dir: Path, sem_id: int) -> Path:
    return data_dir / "sem" / f"sem-{sem_id:05d}.npy"


def save_pixels(path: Path, pixels: FloatArray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, np.asarray(pixels, dtype=np.float64), allow_pickle=False)
    tmp.replace(path)


def sem_view(record: SemImageRecord) -> SEMView:
    """A stored SEM image with its pixel-to-stage map, as :mod:`merge.correlative` takes it
    (its pixels read from its file)."""
    pixels = np.load(Path(record.file), allow_pickle=False)
    if record.matrix is not None:
        matrix = np.asarray(record.matrix, dtype=np.float64)
    else:  # placed before maps were stored: its pixel size along the axes
        matrix = np.diag([record.pixel_x, record.pixel_y])
    return SEMView(np.asarray(pixels, dtype=np.float64), (record.origin_x, record.origin_y), matrix)
