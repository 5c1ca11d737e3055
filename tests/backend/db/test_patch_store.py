"""Crash safety of the patch store: whatever instant a crash hits, nothing is lost or orphaned."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from sqlalchemy.orm import Session

from backend.db.models import PatchRecord, Run
from backend.db.patch_store import (
    dataset_name,
    mark_stored,
    read_merge_detail,
    read_patch,
    reconcile,
    write_merge,
    write_patch,
)
from backend.db.session import make_engine, migrate, session_factory


@pytest.fixture
def session_and_run(tmp_path: Path) -> tuple[Session, Run]:
    url = f"sqlite:///{tmp_path / 'm.sqlite'}"
    migrate(url)
    session = session_factory(make_engine(url))()
    run = Run(
        state="running",
        roi_x=0,
        roi_y=0,
        roi_width=1e-6,
        roi_height=1e-6,
        patch_width=5e-7,
        patch_height=5e-7,
        pixels_x=8,
        pixels_y=8,
        overlap_x=0.3,
        overlap_y=0.3,
        rows=1,
        cols=3,
        instrument="sim://",
        data_file=str(tmp_path / "runs" / "run-1.h5"),
    )
    run.patches = [
        PatchRecord(index=i, row=0, col=i, origin_x=i * 3e-7, origin_y=0.0) for i in range(3)
    ]
    session.add(run)
    session.commit()
    return session, run


def _write(run: Run, index: int) -> str:
    return write_patch(
        Path(run.data_file),
        index,
        np.full((8, 8), float(index)),
        origin=(index * 3e-7, 0.0),
        pixel_size=(6.25e-8, 6.25e-8),
        line_times=np.arange(8.0),
        attrs={"instrument": "sim"},
    )


def test_write_then_commit_round_trip(session_and_run: tuple[Session, Run]) -> None:
    session, run = session_and_run
    mark_stored(session, run.patches[0], _write(run, 0))
    stored = read_patch(Path(run.data_file), 0)
    assert stored.heights[0, 0] == 0.0
    assert stored.origin == (0.0, 0.0)
    assert stored.attrs["instrument"] == "sim"
    assert reconcile(session, run) == []
    with pytest.raises(KeyError):
        read_patch(Path(run.data_file), 1)


def test_crash_between_the_write_and_the_commit_loses_nothing(
    session_and_run: tuple[Session, Run],
) -> None:
    session, run = session_and_run
    _write(run, 1)  # the data reached the disk, the process died before the commit
    notes = reconcile(session, run)
    assert notes == ["patch 1: data on disk adopted after a crash"]
    assert run.patches[1].step == "stored"
    assert run.patches[1].dataset == dataset_name(1)


def test_crash_in_the_middle_of_a_write_leaves_no_orphan(
    session_and_run: tuple[Session, Run],
) -> None:
    session, run = session_and_run
    path = Path(run.data_file)
    path.parent.mkdir(parents=True)
    with h5py.File(path, "a") as f:  # what a write cut short leaves: no 'complete' mark
        f.create_dataset(dataset_name(2), data=np.zeros((8, 8)))
    notes = reconcile(session, run)
    assert notes == ["patch 2: removed data cut short by a crash"]
    with h5py.File(path, "r") as f:
        assert dataset_name(2) not in f
    assert run.patches[2].step == "pending"


def test_a_row_without_data_is_scanned_again(session_and_run: tuple[Session, Run]) -> None:
    session, run = session_and_run
    run.patches[0].step = "stored"  # e.g. the data file was lost
    session.commit()
    notes = reconcile(session, run)
    assert notes == ["patch 0: marked stored but no data; it will be scanned again"]
    assert run.patches[0].step == "pending"


def test_a_retried_patch_replaces_its_earlier_attempt(session_and_run: tuple[Session, Run]) -> None:
    _, run = session_and_run
    path = Path(run.data_file)
    _write(run, 0)
    write_patch(
        path, 0, np.ones((8, 8)), origin=(0.0, 0.0), pixel_size=(1e-8, 1e-8), line_times=np.zeros(8)
    )
    assert read_patch(path, 0).heights[0, 0] == 1.0
    with h5py.File(path, "r") as f:
        assert len(f["patches"]) == 1


def test_a_large_mosaic_is_stored_in_tiles(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from backend.db import patch_store

    heights = np.random.default_rng(2).normal(0.0, 1e-9, (700, 600))
    doc = {"format": "mosaic-afm/mosaic@1", "shape": [700, 600]}
    path = tmp_path / "run.h5"
    small = patch_store.write_merge(path, 1, heights, doc)
    monkeypatch.setattr(patch_store, "CHUNKED_FROM", heights.size - 1)
    large = patch_store.write_merge(path, 2, heights, doc)
    with h5py.File(path, "r") as f:
        assert f[small]["mosaic"].chunks is None
        assert f[large]["mosaic"].chunks == (512, 512)
    back, said = patch_store.read_merge(path, large)
    np.testing.assert_array_equal(back, heights)
    assert said == doc


def test_a_stored_mosaic_is_read_as_a_level_of_detail(tmp_path: Path) -> None:
    heights = np.random.default_rng(3).normal(0.0, 1e-9, (700, 600))
    path = tmp_path / "run.h5"
    group = write_merge(path, 1, heights, {"shape": [700, 600]})
    detail, k, said = read_merge_detail(path, group, 10_000)
    assert k == 7 and detail.shape == (100, 86) and detail.size <= 10_000
    assert detail[0, 0] == pytest.approx(heights[:7, :7].mean(), rel=1e-12)
    assert said == {"shape": [700, 600]}
