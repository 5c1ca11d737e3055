"""Exports of a height map: ``.gwy``, 32-bit float TIFF, PNG (colour bar, scale bar), PLY and
STL surfaces, and ``.npy`` with a ``.json`` beside it. The format follows the file suffix."""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.io.formats.gwy import write_gwy
from merge.io.formats.image import FloatArray, FormatError, top_down_bands
from merge.io.formats.tiff import write_tiff
from merge.io.png import encode_png
from merge.io.preview import render_panels
from merge.render import Mosaic

IntArray = NDArray[np.int64]
EXPORTS = (".gwy", ".tif", ".tiff", ".png", ".ply", ".stl", ".npy")


def _surface(
    heights: FloatArray, pixel_size: tuple[float, float], origin: tuple[float, float]
) -> tuple[FloatArray, IntArray]:
    ny, nx = heights.shape
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    finite = np.isfinite(heights)
    z = np.where(finite, heights, 0.0)
    verts = np.stack(
        [origin[0] + jj * pixel_size[0], origin[1] + ii * pixel_size[1], z], axis=-1
    ).reshape(-1, 3)
    return verts, grid_triangles(finite)


def grid_triangles(finite: NDArray[np.bool_]) -> IntArray:
    """Two triangles per grid cell whose four corners are finite, as ``(m, 3)`` indices into
    the row-major flattened grid (the vertex order of a height map's points)."""
    ny, nx = finite.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    ok = (finite[:-1, :-1] & finite[:-1, 1:] & finite[1:, :-1] & finite[1:, 1:]).ravel()
    faces: IntArray = np.concatenate(
        [
            np.stack([a.ravel(), b.ravel(), d.ravel()], axis=1)[ok],
            np.stack([a.ravel(), d.ravel(), c.ravel()], axis=1)[ok],
        ]
    )
    return faces


def write_ply(path: Path, verts: FloatArray, faces: IntArray) -> None:
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment mosaic-afm surface, metres\n"
        f"element vertex {len(verts)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_rec["n"], face_rec["v"] = 3, faces
    with path.open("wb") as f:
        f.write(header.encode("ascii"))
        f.write(np.asarray(verts, dtype="<f8").tobytes())
        f.write(face_rec.tobytes())


def write_stl(path: Path, verts: FloatArray, faces: IntArray) -> None:
    tri = np.asarray(verts, dtype=np.float64)[faces]  # (F, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.where(length > 0, length, 1.0)
    rec = np.zeros(len(faces), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"], rec["v"] = normals, tri
    with path.open("wb") as f:
        f.write(b"mosaic-afm surface, metres".ljust(80, b" "))
        f.write(struct.pack("<I", len(faces)))
        f.write(rec.tobytes())


def _any_finite(h: FloatArray) -> bool:
    """Whether ``h`` (2-D) holds a finite height, read a few MB at a time."""
    bands = top_down_bands(h.shape[0], h.shape[1], itemsize=h.itemsize, budget=8 << 20)
    return any(bool(np.isfinite(h[lo:hi]).any()) for lo, hi in bands)


def export_heights(
    path: str | Path,
    heights: FloatArray,
    *,
    pixel_size: tuple[float, float],
    origin: tuple[float, float] = (0.0, 0.0),
    document: dict[str, Any] | None = None,
    title: str = "Height",
    channels: Sequence[tuple[str, FloatArray, str]] = (),
) -> Path:
    """Write ``heights`` (metres, rows along +y, NaN = no data) in the format of ``path``'s
    suffix; ``document`` (e.g. a merge's ``mosaic.json``) goes along as metadata.
    ``channels`` (``(title, values, unit)`` on the heights' grid, e.g. the SEM image the
    mosaic was registered on): more channels of a ``.gwy``, more pages of a ``.tif``; the
    other formats hold one map and refuse them."""
    out = Path(path)
    suffix = out.suffix.lower()
    h = np.asarray(heights)  # a memory-mapped mosaic stays mapped
    if h.ndim != 2 or not _any_finite(h):
        raise FormatError(f"{out}: nothing to export (need a 2-D map with finite heights)")
    doc = document or {}
    if channels and suffix not in (".gwy", ".tif", ".tiff"):
        raise FormatError(f"{out}: a {suffix} file holds one map: export .gwy or .tif")
    if suffix == ".gwy":
        meta = {
            "Software": "mosaic-afm",
            **{
                k: json.dumps(v)
                for k, v in doc.items()
                if k in ("method", "parameters", "iterations", "converged", "sem_registration")
            },
        }
        if "patches" in doc:
            meta["Patches"] = json.dumps(
                [
                    {k: p.get(k) for k in ("id", "rotation", "translation", "source")}
                    for p in doc["patches"]
                ]
            )
        write_gwy(
            out,
            h,
            pixel_size=pixel_size,
            origin=origin,
            title=title,
            metadata=meta,
            channels=channels,
        )
    elif suffix in (".tif", ".tiff"):
        write_tiff(out, h, pixel_size=pixel_size, pages=[(t, v) for t, v, _ in channels])
    elif suffix == ".png":
        mosaic = Mosaic(h, origin, pixel_size, np.isfinite(h).astype(np.int32))
        out.write_bytes(
            encode_png(
                render_panels([(title.upper(), mosaic)], size=max(256, min(2048, max(h.shape))))
            )
        )
    elif suffix in (".ply", ".stl"):
        verts, faces = _surface(h, pixel_size, origin)
        (write_ply if suffix == ".ply" else write_stl)(out, verts, faces)
    elif suffix == ".npy":
        np.save(out, h, allow_pickle=False)
        side = {
            "pixel_size": list(pixel_size),
            "origin": list(origin),
            "units": "m",
            "channel": title,
            **({"document": doc} if doc else {}),
        }
        out.with_suffix(".json").write_text(json.dumps(side, indent=1) + "\n", encoding="utf-8")
    else:
        raise FormatError(
            f"{out}: unknown export format {suffix!r}; use one of {', '.join(EXPORTS)}"
        )
    return out
