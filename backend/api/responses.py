"""What the API sends beside JSON: height maps as ``.npy`` files and as PNG pictures (the AFM
colour map with a nm colour bar and a scale bar), shared by the runs', merges', SEM and
instrument routes."""

from __future__ import annotations

import io
from typing import Any

import numpy as np
from fastapi import Response

from merge.io.png import encode_png
from merge.io.preview import render_panels
from merge.render import Mosaic

NPY = "application/x-npy"
PNG_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {}}, "description": "a PNG image"}
}


def png_response(panels: list[tuple[str, Mosaic]], *, size: int) -> Response:
    """Height maps in the AFM colour map with a nm colour bar and a scale bar, as PNG."""
    return Response(encode_png(render_panels(panels, size=size)), media_type="image/png")


def height_map(
    heights: np.ndarray, origin: tuple[float, float], pixel: tuple[float, float]
) -> Mosaic:
    """Heights (ny, nx), metres, with their origin and pixel size, as a picture's panel."""
    return Mosaic(heights, origin, pixel, np.isfinite(heights).astype(np.int32))


def npy_response(array: np.ndarray, filename: str) -> Response:
    """``array`` as a float64 ``.npy`` attachment named ``filename``."""
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array, dtype=np.float64), allow_pickle=False)
    return Response(
        buffer.getvalue(),
        media_type=NPY,
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )
