"""SEM images in the data dir, and the pixel size a vendor wrote into a TIFF."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import tifffile
from numpy.typing import NDArray

from merge.io.formats.image import FormatError
from merge.io.formats.tiff import check_declared

FloatArray = NDArray[np.float64]

_UNITS = {"m": 1.0, "mm": 1e-3, "µm": 1e-6, "um": 1e-6, "nm": 1e-9, "pm": 1e-12}


#: Values an SEM TIFF may declare (RGB counts three a pixel): 32 Mi, an SEM's largest usual
#: grey frame (8192 x 4096); a larger image is binned before upload.
MAX_SEM_VALUES = 1 << 25


class TiffError(ValueError):
    """The upload is not a usable TIFF image; the message says why."""


def _fei(meta: dict[str, Any]) -> tuple[float, float] | None:
    scan = meta.get("Scan") or meta.get("EScan") or {}
    px, py = scan.get("PixelWidth"), scan.get("PixelHeight", scan.get("PixelWidth"))
    if isinstance(px, int | float) and isinstance(py, int | float) and px > 0 and py > 0:
        return float(px), float(py)
    return None


def _zeiss(meta: dict[str, Any]) -> tuple[float, float] | None:
    entry = meta.get("ap_image_pixel_size") or meta.get("ap_pixel_size")
    if not entry or len(entry) < 2 or not isinstance(entry[1], int | float):
        return None
    scale = _UNITS.get(entry[2] if len(entry) > 2 else "nm")
    if scale is None or entry[1] <= 0:
        return None
    size = float(entry[1]) * scale
    return size, size


def read_sem_tiff(data: bytes) -> tuple[FloatArray, tuple[float, float] | None, str]:
    """Grey levels (ny, nx) and the vendor's pixel size (metres) if the TIFF carries one,
    with the name of the source of that size. A page declaring more than
    :data:`MAX_SEM_VALUES` values is refused from its header, before anything is decoded."""
    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            page = tif.pages.first
            check_declared(page, "the TIFF", limit=MAX_SEM_VALUES)
            pixels = np.asarray(page.asarray(), dtype=np.float32)
            size: tuple[float, float] | None = None
            source = "request"
            if tif.is_fei and tif.fei_metadata:
                size, source = _fei(tif.fei_metadata), "FEI/Thermo TIFF tags"
            elif tif.is_sem and tif.sem_metadata:
                size, source = _zeiss(tif.sem_metadata), "Zeiss TIFF tags"
    except FormatError as exc:
        raise TiffError(str(exc)) from None
    except Exception as exc:  # tifffile raises many kinds on a bad file
        raise TiffError(f"not a readable TIFF image ({type(exc).__name__}: {exc})") from None
    if pixels.ndim == 3 and pixels.shape[-1] in (3, 4):
        pixels = pixels[..., :3].mean(axis=-1, dtype=np.float32)  # RGB(A) export: grey levels
    if pixels.ndim != 2 or min(pixels.shape) < 8:
        raise TiffError(f"need a 2-D grey image of at least 8 x 8 pixels, got {pixels.shape}")
    return pixels.astype(np.float64), size, source if size is not None else "request"


def sem_path(data_dir: Path, sem_id: int) -> Path:
    return data_dir / "sem" / f"sem-{sem_id:05d}.npy"


def save_pixels(path: Path, pixels: FloatArray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, np.asarray(pixels, dtype=np.float64), allow_pickle=False)
    tmp.replace(path)
