"""Patch-set files: ``manifest.json`` beside one height file per patch (docs/design.md).

This is the I/O edge of the merge engine: it turns files into a validated :class:`PatchSet` and
back. Every problem is a :class:`PatchSetError` whose message names the patch and the fix.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from merge.core.errors import PatchSetError
from merge.core.patchset import FloatArray, Patch, PatchSet

FORMAT = "mosaic-afm/patchset@1"

#: A reader for one height-file type: path -> 2-D heights in metres.
HeightReader = Callable[[Path], FloatArray]


def _read_npy(path: Path) -> FloatArray:
    arr = np.load(path, allow_pickle=False)
    return np.asarray(arr)


READERS: dict[str, HeightReader] = {".npy": _read_npy}


def _vendor(path: Path, channel: Any) -> HeightReader | None:
    """A reader of an AFM file of any vendor format (:mod:`merge.io.formats`), of its
    ``channel`` (topography by default)."""
    from merge.io.formats import read_image, reader_for

    if reader_for(path) is None:
        return None
    wanted = channel if isinstance(channel, str) and channel else None
    return lambda p: read_image(p, channel=wanted).heights


def read_patch_set(
    manifest: str | Path, *, readers: Mapping[str, HeightReader] | None = None
) -> PatchSet:
    """Read and validate a patch set from its ``manifest.json``.

    Parameters
    ----------
    manifest : path
        The manifest file (or the folder holding ``manifest.json``).
    readers : mapping, optional
        Extra height-file readers by lower-case suffix, tried before the built-in ones:
        ``.npy`` and every AFM format of :mod:`merge.io.formats` (an entry's ``channel``
        names the channel to read; topography by default).

    Raises
    ------
    PatchSetError
        For a missing or malformed manifest, a missing or unreadable height file, or any patch
        that fails validation (see :class:`Patch`).
    """
    path = Path(manifest)
    if path.is_dir():
        path = path / "manifest.json"
    if not path.is_file():
        raise PatchSetError(f"manifest not found: {path}")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PatchSetError(f"manifest {path} is not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise PatchSetError(f"manifest {path} must hold a JSON object")
    fmt = doc.get("format", FORMAT)
    if not isinstance(fmt, str) or not fmt.startswith("mosaic-afm/patchset@"):
        raise PatchSetError(f"manifest {path}: format must be {FORMAT!r}, got {fmt!r}")
    if fmt != FORMAT:
        raise PatchSetError(f"manifest {path}: this version reads {FORMAT!r}, not {fmt!r}")
    units = doc.get("units", "m")
    if units != "m":
        raise PatchSetError(f"manifest {path}: units must be 'm' (SI metres), got {units!r}")
    entries = doc.get("patches")
    if not isinstance(entries, list):
        raise PatchSetError(f"manifest {path}: 'patches' must be a list")
    extra = readers or {}
    patches = [_read_entry(entry, k, path.parent, extra) for k, entry in enumerate(entries)]
    return PatchSet(patches)


def _read_entry(entry: Any, k: int, folder: Path, readers: Mapping[str, HeightReader]) -> Patch:
    if not isinstance(entry, dict):
        raise PatchSetError(f"patch #{k} in the manifest must be an object")
    pid = entry.get("id")
    if not isinstance(pid, str) or not pid:
        raise PatchSetError(f"patch #{k} in the manifest needs a non-empty string 'id'")
    name = f"patch {pid!r}"
    for key in ("file", "origin", "pixel_size"):
        if key not in entry:
            raise PatchSetError(f"{name}: missing '{key}' in the manifest")
    file = entry["file"]
    if not isinstance(file, str) or not file:
        raise PatchSetError(f"{name}: 'file' must be a file name")
    fpath = (folder / file).resolve()
    if not fpath.is_file():
        raise PatchSetError(f"{name}: height file not found: {fpath}")
    reader: HeightReader | None
    try:  # indexing, not .get: a mapping given may resolve suffixes it does not list
        reader = readers[fpath.suffix.lower()]
    except KeyError:
        reader = READERS.get(fpath.suffix.lower()) or _vendor(fpath, entry.get("channel"))
    if reader is None:
        from merge.io.formats import READABLE

        raise PatchSetError(f"{name}: no reader for {fpath.suffix!r} files (known: {READABLE})")
    try:
        heights = reader(fpath)
    except PatchSetError:
        raise
    except Exception as exc:  # any reader failure is a bad input file, named as such
        raise PatchSetError(f"{name}: cannot read {fpath}: {exc}") from None
    order = entry.get("order", k)
    if not isinstance(order, int) or isinstance(order, bool):
        raise PatchSetError(f"{name}: 'order' must be an integer, got {order!r}")
    row, col = entry.get("row"), entry.get("col")
    for key, val in (("row", row), ("col", col)):
        if val is not None and (not isinstance(val, int) or isinstance(val, bool)):
            raise PatchSetError(f"{name}: '{key}' must be an integer, got {val!r}")
    return Patch(
        id=pid,
        heights=heights,
        origin=entry["origin"],
        pixel_size=entry["pixel_size"],
        order=order,
        row=row,
        col=col,
        source=str(fpath),
    )


def write_patch_set(
    patch_set: PatchSet, folder: str | Path, *, extra: Mapping[str, Any] | None = None
) -> Path:
    """Write ``manifest.json`` and one ``<id>.npy`` per patch into ``folder``; return the manifest.

    ``extra`` adds top-level keys to the manifest (never overriding the format's own).
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for p in patch_set:
        fname = f"{p.id}.npy"
        np.save(out / fname, p.heights)
        entry: dict[str, Any] = {
            "id": p.id,
            "file": fname,
            "order": p.order,
            "origin": [_num(v) for v in p.origin],
            "pixel_size": [_num(v) for v in p.pixel_size],
        }
        if p.row is not None:
            entry["row"] = p.row
        if p.col is not None:
            entry["col"] = p.col
        entries.append(entry)
    doc: dict[str, Any] = dict(extra or {})
    doc.update({"format": FORMAT, "units": "m", "patches": entries})
    path = out / "manifest.json"
    path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return path


def _num(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError(f"cannot write non-finite number {v}")
    return float(v)
