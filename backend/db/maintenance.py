"""A data directory's health and its copies: ``mosaic-afm check`` and ``mosaic-afm backup``.

:func:`check_data_dir` verifies the database against the run files: the database's own
integrity, every stored patch readable and complete in its run's file, every finished merge's
result readable, and no run file nobody knows about. :func:`backup_data_dir` makes a
consistent copy while a server may be writing: the run files first (each copy re-read until
it opens whole: a patch being written at that instant is retried), then the database through
SQLite's online backup. A patch stored between the two is in the database copy but not in its
file copy, which the restored server's start-up reconciliation sends back to ``pending``: the
copy never claims data it does not hold. Paths in the database are relative, so the copy
works wherever it is put.
"""

from __future__ import annotations

import shutil
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

#: Files of the data directory that are the database or belong to a running server.
_NOT_COPIED = frozenset({"mosaic.sqlite", "mosaic.sqlite-wal", "mosaic.sqlite-shm",
                         "merge-worker.pid"})  # fmt: skip


@dataclass
class CheckReport:
    """What :func:`check_data_dir` found: ``problems`` (empty when healthy) and ``notes``."""

    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def _database(data_dir: Path) -> Path:
    path = data_dir / "mosaic.sqlite"
    if not path.is_file():
        raise FileNotFoundError(f"{data_dir} has no database (mosaic.sqlite): not a data directory")
    return path


def check_data_dir(data_dir: Path) -> CheckReport:
    """Verify ``data_dir`` (read only); see the module notes for what is checked."""
    report = CheckReport()
    path = _database(data_dir)
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            integrity = db.execute("PRAGMA integrity_check").fetchone()[0]
            runs = db.execute("SELECT id, state, data_file FROM runs ORDER BY id").fetchall()
            stored = db.execute(
                "SELECT run_id, \"index\" FROM patches WHERE step = 'stored' ORDER BY run_id, 2"
            ).fetchall()
            merges = db.execute(
                "SELECT id, run_id, result_group FROM merge_jobs WHERE state = 'done'"
            ).fetchall()
        finally:
            db.close()
    except sqlite3.DatabaseError as exc:
        report.problems.append(f"database {path.name}: cannot be read ({exc})")
        return report
    if integrity != "ok":
        report.problems.append(f"database {path.name}: integrity check says {integrity!r}")
    by_run: dict[int, list[int]] = {}
    for run_id, index in stored:
        by_run.setdefault(run_id, []).append(index)
    known: set[Path] = set()
    for run_id, state, data_file in runs:
        file = Path(data_file) if Path(data_file).is_absolute() else data_dir / data_file
        known.add(file.resolve())
        indices = by_run.get(run_id, [])
        groups = [g for _, r, g in merges if r == run_id and g]
        if not indices and not groups:
            continue
        report.problems.extend(f"run {run_id} ({state}): {p}" for p in
                               _check_file(file, indices, groups))  # fmt: skip
        report.notes.append(f"run {run_id}: {len(indices)} stored patches, {len(groups)} merges")
    runs_dir = data_dir / "runs"
    for orphan in sorted(runs_dir.glob("*.h5")) if runs_dir.is_dir() else []:
        if orphan.resolve() not in known:
            report.notes.append(f"{orphan.relative_to(data_dir)}: no run refers to it")
    return report


def _check_file(file: Path, indices: list[int], groups: list[str]) -> list[str]:
    if not file.is_file():
        return [f"its file {file.name} is missing"]
    problems = []
    try:
        with h5py.File(file, "r") as f:
            for index in indices:
                name = f"patches/{index:05d}"
                if name not in f or not f[name].attrs.get("complete", False):
                    problems.append(f"patch {index} is stored in the database, not in {file.name}")
                    continue
                data = np.asarray(f[name][()])
                if data.ndim != 2:
                    problems.append(f"patch {index}: data of shape {data.shape}")
            for group in groups:
                if group not in f or "mosaic" not in f[group]:
                    problems.append(f"merge result {group} is missing from {file.name}")
                else:
                    f[group]["mosaic"][()]  # read whole: a damaged chunk raises here
    except (OSError, KeyError, ValueError) as exc:
        problems.append(f"its file {file.name} cannot be read ({exc})")
    return problems


def _copy_whole(source: Path, target: Path, *, attempts: int = 10, pause: float = 0.2) -> None:
    """Copy an HDF5 file and re-read the copy; retry while a writer catches it mid-write."""
    for attempt in range(attempts):
        shutil.copy2(source, target)
        try:
            with h5py.File(target, "r") as f:
                f.visititems(lambda _name, obj: dict(obj.attrs) and None)
            return
        except (OSError, KeyError, ValueError):
            if attempt + 1 == attempts:
                raise
            time.sleep(pause)


def backup_data_dir(data_dir: Path, target: Path) -> list[str]:
    """Copy ``data_dir`` to ``target`` (new or empty) consistently; return what was copied."""
    database = _database(data_dir)
    if target.exists() and any(target.iterdir()):
        raise FileExistsError(f"{target} is not empty: give a new folder for the backup")
    target.mkdir(parents=True, exist_ok=True)
    copied: list[str] = []
    for source in sorted(data_dir.rglob("*")):
        rel = source.relative_to(data_dir)
        if source.is_dir() or rel.as_posix() in _NOT_COPIED or rel.parts[0] == "quarantine":
            continue
        (target / rel).parent.mkdir(parents=True, exist_ok=True)
        if source.suffix == ".h5":
            _copy_whole(source, target / rel)
        else:
            shutil.copy2(source, target / rel)
        copied.append(rel.as_posix())
    # the database last: whatever it says stored, the files copied before hold or reconcile
    source_db = sqlite3.connect(f"file:{database}?mode=ro", uri=True)
    target_db = sqlite3.connect(target / database.name)
    try:
        source_db.backup(target_db)
    finally:
        target_db.close()
        source_db.close()
    copied.append(database.name)
    return copied
