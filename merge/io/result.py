"""Merge-result files (docs/design.md): ``mosaic.npy``, ``mosaic.json`` and ``preview.png``."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.core.patchset import PatchSet
from merge.core.transforms import PatchTransform
from merge.io.preview import write_preview
from merge.refine.scanner import ScanDistortion
from merge.render import Mosaic, render_mosaic
from merge.report import MergeResult

FloatArray = NDArray[np.float64]
FORMAT = "mosaic-afm/mosaic@1"
#: Longer side of each panel of ``preview.png``, pixels.
PREVIEW_SIDE = 420


def _clean(v: float) -> float | None:
    """JSON has no NaN or infinity: those become null."""
    return float(v) if math.isfinite(v) else None


def result_document(result: MergeResult, patch_set: PatchSet | None = None) -> dict[str, Any]:
    """The ``mosaic.json`` document of a result."""
    m = result.mosaic
    sources = {p.id: p.source for p in patch_set} if patch_set is not None else {}
    return {
        "format": FORMAT,
        "units": "m",
        "origin": [float(m.origin[0]), float(m.origin[1])],
        "pixel_size": [float(m.pixel_size[0]), float(m.pixel_size[1])],
        "shape": [int(m.heights.shape[0]), int(m.heights.shape[1])],
        "method": result.method,
        "parameters": result.config.as_dict(),
        "iterations": result.iterations,
        "converged": result.converged,
        "residual_history": [_clean(v) for v in result.history],
        "warnings": list(result.warnings),
        "timings": {k: round(v, 4) for k, v in result.timings.items()},
        "patches": [
            {
                "id": r.id,
                "rotation": np.asarray(r.rotation).tolist(),
                "translation": np.asarray(r.translation).tolist(),
                "transform": {
                    "model": "rigid+zplane",
                    "rotation": r.transform.R.tolist(),
                    "translation": r.transform.t.tolist(),
                    "z_slope": r.transform.slope.tolist(),
                    "centre": r.transform.centre.tolist(),
                },
                "overlaps": r.overlaps,
                "correspondences": r.correspondences,
                "residual_rms": _clean(r.residual_rms),
                "xy_constrained": r.xy_constrained,
                "xy_sigma": _clean(r.xy_sigma),
                "z_sigma": _clean(r.z_sigma),
                **({"source": sources[r.id]} if sources.get(r.id) else {}),
            }
            for r in result.patches
        ],
        **({"scan_distortion": _distortion(result.distortion)} if result.distortion else {}),
    }


def _distortion(d: ScanDistortion) -> dict[str, Any]:
    """The scanner's bend taken out of every patch before the transforms apply: metres along y
    of each row and along x of each column (true minus nominal place), with their sigmas."""
    return {
        "rows": d.rows.tolist(),
        "cols": d.cols.tolist(),
        "rows_sigma": d.rows_sigma.tolist(),
        "cols_sigma": d.cols_sigma.tolist(),
        "peak_to_valley": list(d.peak_to_valley),
        "observations": list(d.observations),
        "significant": list(d.significant),
    }


def write_result(
    result: MergeResult,
    folder: str | Path,
    *,
    patch_set: PatchSet | None = None,
    preview: bool = True,
) -> Path:
    """Write the result files into ``folder`` (created if needed); return ``mosaic.json``'s path.

    With ``patch_set`` given, ``preview.png`` shows the nominal placement beside the merge.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "mosaic.npy", np.asarray(result.mosaic.heights, dtype=np.float64))
    doc = result_document(result, patch_set)
    path = out / "mosaic.json"
    path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    if preview and patch_set is not None:
        m = result.mosaic
        ny, nx = m.heights.shape
        bounds = (
            m.origin[0],
            m.origin[1],
            m.origin[0] + (nx - 1) * m.pixel_size[0],
            m.origin[1] + (ny - 1) * m.pixel_size[1],
        )
        # the nominal placement only as fine as the preview shows it (a panel's longer side:
        # PREVIEW_SIDE), not a second mosaic of the merge's size
        coarse = max(1.0, max(ny, nx) / PREVIEW_SIDE)
        pitch = (m.pixel_size[0] * coarse, m.pixel_size[1] * coarse)
        before = render_mosaic(patch_set.patches, pixel_size=pitch, bounds=bounds)
        write_preview(str(out / "preview.png"), before, m, size=PREVIEW_SIDE)
    return path


@dataclass(frozen=True)
class StoredResult:
    """A result read back from its files: the mosaic and the ``mosaic.json`` document."""

    mosaic: Mosaic
    document: dict[str, Any]

    @property
    def transforms(self) -> dict[str, PatchTransform]:
        """``{patch id: T_mosaic_patch}``: the full model when stored, else the rigid one."""
        out = {}
        for p in self.document["patches"]:
            full = p.get("transform")
            if full and full.get("model") == "rigid+zplane":
                out[p["id"]] = PatchTransform(
                    full["rotation"], full["translation"], full["z_slope"], full["centre"]
                )
            else:
                out[p["id"]] = PatchTransform(p["rotation"], p["translation"])
        return out


def read_result(folder: str | Path) -> StoredResult:
    """Read ``mosaic.npy`` and ``mosaic.json`` from ``folder``."""
    base = Path(folder)
    if base.is_file():
        base = base.parent
    try:
        doc = json.loads((base / "mosaic.json").read_text(encoding="utf-8"))
        # memory-mapped: a large mosaic is read from the disk as it is used, not all at once
        heights = np.load(base / "mosaic.npy", allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError) as exc:
        raise ValueError(f"not a merge result folder: {base} ({exc})") from None
    shape = tuple(doc.get("shape", heights.shape))
    if heights.ndim != 2 or tuple(heights.shape) != shape:
        raise ValueError(f"{base}: mosaic.npy has shape {heights.shape}, mosaic.json says {shape}")
    mosaic = Mosaic(
        heights=np.asarray(heights, dtype=np.float64),  # no copy when it is float64 already
        origin=(float(doc["origin"][0]), float(doc["origin"][1])),
        pixel_size=(float(doc["pixel_size"][0]), float(doc["pixel_size"][1])),
        coverage=np.isfinite(heights).astype(np.int32),
    )
    return StoredResult(mosaic=mosaic, document=doc)
