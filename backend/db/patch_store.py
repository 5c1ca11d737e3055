"""Patch data in HDF5 (one file per run) and its reconciliation with the database.

Write order, so that a crash at any instant leaves no database row pointing at missing data
and no data nobody knows about:

1. the heights go into ``/patches/<index>`` with their attributes, ``complete`` set last;
2. the file is flushed and fsynced;
3. only then the patch row is committed as ``stored``.

At start-up :func:`reconcile` repairs what a crash can leave: a complete dataset whose row
was not yet committed is adopted (no patch is lost), an incomplete dataset is removed, and a
row that says ``stored`` without a complete dataset goes back to ``pending`` (a patch whose
data is not in the store has not been scanned).
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray
from sqlalchemy.orm import Session

from backend.db.models import Event, PatchRecord, Run
from merge.io.detail import block_means, detail_step

FloatArray = NDArray[np.float64]


_LOCKS: dict[str, threading.RLock] = {}
_LOCKS_GUARD = threading.Lock()


@contextmanager
def locked(path: Path) -> Iterator[None]:
    """Serialise every access to one run file in this process (HDF5 allows one writer)."""
    key = str(Path(path).resolve())
    with _LOCKS_GUARD:
        lock = _LOCKS.setdefault(key, threading.RLock())
    with lock:
        yield


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def dataset_name(index: int) -> str:
    return f"patches/{index:05d}"


def merge_group(job_id: int) -> str:
    return f"merges/{job_id:05d}"


@dataclass(frozen=True)
class StoredPatch:
    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    line_times: FloatArray
    attrs: dict[str, Any]


def write_patch(
    path: Path,
    index: int,
    heights: FloatArray,
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    line_times: FloatArray,
    attrs: dict[str, Any] | None = None,
) -> str:
    """Write one patch durably (steps 1 and 2 of the module notes); return its dataset name."""
    path.parent.mkdir(parents=True, exist_ok=True)
    name = dataset_name(index)
    with locked(path), h5py.File(path, "a") as f:
        if name in f:
            del f[name]  # an earlier, unfinished attempt of the same patch
        ds = f.create_dataset(name, data=np.asarray(heights, dtype=np.float64))
        ds.attrs["origin"] = np.asarray(origin, dtype=np.float64)
        ds.attrs["pixel_size"] = np.asarray(pixel_size, dtype=np.float64)
        ds.attrs["line_times"] = np.asarray(line_times, dtype=np.float64)
        ds.attrs["units"] = "m"
        for key, value in (attrs or {}).items():
            ds.attrs[key] = value
        ds.attrs["complete"] = True  # last: a dataset without it was cut short
        f.flush()
    _fsync(path)
    return name


def reject_patch(path: Path, index: int, attempt: int) -> str | None:
    """Keep a stored patch the quality gate failed out of the way of its re-scan: its dataset
    moves to ``rejected/<index>-try<attempt>`` (nothing is deleted; a crash before the re-scan
    is stored leaves the patch pending, not the rejected scan adopted). Return where it went
    (None if the patch was not stored)."""
    name = dataset_name(index)
    target = f"rejected/{index:05d}-try{attempt}"
    with locked(path), h5py.File(path, "a") as f:
        if name not in f:
            return None
        if target in f:
            del f[target]
        f.require_group("rejected")
        f.move(name, target)
        f.flush()
    _fsync(path)
    return target


def read_patch(path: Path, index: int) -> StoredPatch:
    """Read a complete patch; KeyError when it is not stored."""
    with locked(path), h5py.File(path, "r") as f:
        name = dataset_name(index)
        if name not in f or not f[name].attrs.get("complete", False):
            raise KeyError(f"patch {index} is not stored in {path.name}")
        ds = f[name]
        extra = {
            k: v
            for k, v in ds.attrs.items()
            if k not in ("origin", "pixel_size", "line_times", "units", "complete")
        }
        return StoredPatch(
            heights=np.asarray(ds[()], dtype=np.float64),
            origin=(float(ds.attrs["origin"][0]), float(ds.attrs["origin"][1])),
            pixel_size=(float(ds.attrs["pixel_size"][0]), float(ds.attrs["pixel_size"][1])),
            line_times=np.asarray(ds.attrs["line_times"], dtype=np.float64),
            attrs=extra,
        )


def _scan(path: Path) -> tuple[set[int], set[int]]:
    """Indices of complete and of incomplete patch datasets in the file."""
    complete: set[int] = set()
    partial: set[int] = set()
    if not path.exists():
        return complete, partial
    with locked(path), h5py.File(path, "r") as f:
        group = f.get("patches")
        if group is None:
            return complete, partial
        for key in group:
            (complete if group[key].attrs.get("complete", False) else partial).add(int(key))
    return complete, partial


def reconcile(session: Session, run: Run) -> list[str]:
    """Make the database and the run's file agree after a crash; return what was repaired."""
    path = run.file
    complete, partial = _scan(path)
    notes: list[str] = []
    if partial:
        with locked(path), h5py.File(path, "a") as f:
            for index in sorted(partial):
                del f[dataset_name(index)]
        notes.extend(f"patch {i}: removed data cut short by a crash" for i in sorted(partial))
    for patch in run.patches:
        has_data = patch.index in complete
        if patch.step == "stored" and not has_data:
            patch.step, patch.stored_at, patch.dataset = "pending", None, None
            notes.append(
                f"patch {patch.index}: marked stored but no data; it will be scanned again"
            )
        elif patch.step != "stored" and has_data:
            patch.step, patch.dataset = "stored", dataset_name(patch.index)
            patch.stored_at = datetime.now(UTC)
            notes.append(f"patch {patch.index}: data on disk adopted after a crash")
    known = {p.index for p in run.patches}
    stray = sorted(complete - known)
    if stray:
        with locked(path), h5py.File(path, "a") as f:
            for index in stray:
                del f[dataset_name(index)]
        notes.extend(f"patch {i}: removed data of no planned patch" for i in stray)
    for note in notes:
        session.add(Event(run_id=run.id, kind="reconcile", message=note, data={}))
    session.commit()
    return notes


def mark_stored(session: Session, patch: PatchRecord, dataset: str) -> None:
    """Step 3: commit the row only after :func:`write_patch` returned."""
    patch.step, patch.dataset, patch.stored_at = "stored", dataset, datetime.now(UTC)
    session.commit()


#: Pixels from which a stored mosaic is written in tiles of MOSAIC_TILE x MOSAIC_TILE (HDF5
#: chunks); smaller ones are one contiguous block, which reads fastest whole.
CHUNKED_FROM = 1 << 22
MOSAIC_TILE = 512
#: The group of a run's live mosaic, as the live merge left it when the run ended.
LIVE_GROUP = "live"


def write_merge(path: Path, job_id: int, heights: FloatArray, document: dict[str, Any]) -> str:
    """Store a merge result (mosaic heights and its ``mosaic.json`` document) durably."""
    return write_mosaic(path, merge_group(job_id), heights, document)


def write_mosaic(path: Path, name: str, heights: FloatArray, document: dict[str, Any]) -> str:
    """Store mosaic heights and their document durably as group ``name``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with locked(path), h5py.File(path, "a") as f:
        if name in f:
            del f[name]
        group = f.create_group(name)
        h = np.asarray(heights, dtype=np.float64)
        # a large mosaic in tiles: a reader takes the part it shows without reading the whole
        tiles = (min(h.shape[0], MOSAIC_TILE), min(h.shape[1], MOSAIC_TILE))
        group.create_dataset("mosaic", data=h, chunks=tiles if h.size > CHUNKED_FROM else None)
        group.attrs["document"] = json.dumps(document)
        group.attrs["complete"] = True
        f.flush()
    _fsync(path)
    return name


def read_merge_detail(
    path: Path, group: str, budget: int
) -> tuple[FloatArray, int, dict[str, Any]]:
    """A stored merge result's mosaic as a level of detail of at most ``budget`` heights (the
    means of ``k`` x ``k`` blocks, read a band at a time: a large mosaic is never read whole),
    ``k`` and its document; KeyError if absent."""
    with locked(path), h5py.File(path, "r") as f:
        if group not in f or not f[group].attrs.get("complete", False):
            raise KeyError(f"merge result {group} is not stored in {path.name}")
        g = f[group]
        k = detail_step(g["mosaic"].shape, budget)
        return block_means(g["mosaic"], k), k, json.loads(g.attrs["document"])


def read_merge_document(path: Path, group: str) -> dict[str, Any]:
    """A stored merge result's document alone (its mosaic not read); KeyError if absent."""
    with locked(path), h5py.File(path, "r") as f:
        if group not in f or not f[group].attrs.get("complete", False):
            raise KeyError(f"merge result {group} is not stored in {path.name}")
        document: dict[str, Any] = json.loads(f[group].attrs["document"])
        return document


def read_merge(path: Path, group: str) -> tuple[FloatArray, dict[str, Any]]:
    """A stored merge result: mosaic heights (metres) and its document; KeyError if absent."""
    with locked(path), h5py.File(path, "r") as f:
        if group not in f or not f[group].attrs.get("complete", False):
            raise KeyError(f"merge result {group} is not stored in {path.name}")
        g = f[group]
        return np.asarray(g["mosaic"][()], dtype=np.float64), json.loads(g.attrs["document"])
