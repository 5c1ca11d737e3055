"""A full disk during a patch write, a commit or a merge: the instrument ends safe, nothing
stored is lost, and once space returns the run resumes and merges run, without a restart.

The data directory lives on a small tmpfs the test mounts (it needs root, as CI has)."""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import pytest
from sqlalchemy import event
from sqlalchemy.exc import OperationalError

from tests.backend.api.conftest import Server, open_server, plan
from tests.backend.api.test_faults import _tip_is_safe


@contextlib.contextmanager
def small_disk(where: Path, size: str = "24m") -> Iterator[Path]:
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
        capture_output=True,
        check=False,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {done.stderr.decode().strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def fill(disk: Path) -> Path:
    """Write a ballast file until the disk refuses more."""
    ballast = disk / "ballast"
    chunk = b"\0" * (256 * 1024)
    with contextlib.suppress(OSError), open(ballast, "wb") as f:
        while True:
            f.write(chunk)
            f.flush()
    return ballast


@pytest.fixture
def disk_server(tmp_path: Path) -> Iterator[tuple[Server, Path]]:
    with small_disk(tmp_path / "disk") as disk:
        for server in open_server(disk / "data", disk_reserve=0):
            yield server, disk


def _wait(what: str, until: object, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not until():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"never: {what}"
        time.sleep(0.05)


def _start(server: Server) -> int:
    run = server.create(plan(pixels=(32, 32)))
    server.post(f"/api/runs/{run['id']}/start")
    return int(run["id"])


def test_a_full_disk_mid_run_ends_safe_then_the_run_resumes(
    disk_server: tuple[Server, Path],
) -> None:
    server, disk = disk_server
    rid = _start(server)
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2)
    ballast = fill(disk)
    ended = server.wait_state(rid, "failed", "fault", "completed", timeout=120)
    assert ended["state"] == "failed", ended
    assert "is full" in ended["message"] and "data" in ended["message"], ended["message"]
    _tip_is_safe(server)
    status = server.client.get("/api/instrument").json()
    assert status["safe_state"] is True and status["loop_engaged"] is False
    stored = ended["progress"]["stored"]
    # while full: no other run starts, and the answer says why (507)
    other = server.post("/api/runs", plan())
    if other.status_code == 201:
        r = server.post(f"/api/runs/{other.json()['id']}/start")
        assert r.status_code == 507, r.text
    else:
        assert other.status_code == 507, other.text
    assert "data directory" in (r if other.status_code == 201 else other).json()["detail"]
    os.remove(ballast)
    # space is back: the end is recorded without a restart, and the run resumes
    _wait("the failure recorded", lambda: server.services.runner.unrecorded(rid) is None)
    assert server.post(f"/api/runs/{rid}/resume").status_code == 202
    done = server.wait_state(rid, "completed", "failed", timeout=120)
    assert done["state"] == "completed", done
    assert done["progress"]["stored"] == done["progress"]["total"] >= stored
    with h5py.File(Path(server.data_dir) / "runs" / f"run-{rid:05d}.h5", "r") as f:
        assert len(f["patches"]) == done["progress"]["total"]
        assert all(f["patches"][n].attrs["complete"] for n in f["patches"])


def test_no_run_starts_without_the_reserve(tmp_path: Path) -> None:
    for server in open_server(tmp_path, disk_reserve=10**15):
        run = server.create(plan())
        r = server.post(f"/api/runs/{run['id']}/start")
        assert r.status_code == 507, r.text
        assert "data directory" in r.json()["detail"] and "reserve" in r.json()["detail"]
        assert server.client.get(f"/api/runs/{run['id']}").json()["state"] == "planned"


def test_a_full_disk_during_a_merge_fails_it_and_the_next_one_runs(
    disk_server: tuple[Server, Path], caplog: pytest.LogCaptureFixture
) -> None:
    server, disk = disk_server
    rid = _start(server)
    assert server.wait_state(rid, "completed", "failed", timeout=120)["state"] == "completed"
    r = server.post(f"/api/runs/{rid}/merges", {"method": "default"})
    assert r.status_code == 202, r.text
    job = r.json()["id"]
    ballast = fill(disk)  # the worker starts now; its result has nowhere to go
    try:
        # full until the merge has failed on it, however long that takes (a fixed wait let
        # a slow merge write its result after the disk had room again); the failure is
        # recorded once the database can write again
        deadline = time.monotonic() + 120.0
        while not any(r.getMessage() == f"merge {job} failed" for r in caplog.records):
            assert time.monotonic() < deadline, "the merge never met the full disk"
            time.sleep(0.1)
    finally:
        os.remove(ballast)
    ended = server.wait_merge(job)
    print("merge during a full disk:", ended["state"], ended["message"])
    assert ended["state"] == "failed", ended
    assert "full" in ended["message"], ended["message"]
    again = server.post(f"/api/runs/{rid}/merges", {"method": "default"})
    assert again.status_code == 202, again.text
    assert server.wait_merge(again.json()["id"])["state"] == "done"


@pytest.mark.parametrize("site", ["patch write", "commit"])
def test_enospc_at_each_write_site_ends_safe_and_the_run_resumes(
    server: Server, site: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same, with the disk's refusal injected at one write site of the worker."""
    full = threading.Event()
    if site == "patch write":
        import backend.acquisition.patch_loop as runner_module

        real = runner_module.write_patch

        def write_patch(*args: Any, **kwargs: Any) -> str:
            if full.is_set():
                raise OSError(errno.ENOSPC, "No space left on device")
            return real(*args, **kwargs)

        monkeypatch.setattr(runner_module, "write_patch", write_patch)
    else:

        def before_commit(_session: Any) -> None:
            if full.is_set() and threading.current_thread().name.startswith(("run-", "super")):
                raise OperationalError("COMMIT", {}, Exception("database or disk is full"))

        event.listen(server.services.sessions, "before_commit", before_commit)
    rid = _start(server)
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2)
    full.set()
    ended = server.wait_state(rid, "failed", "fault", "completed", timeout=120)
    assert ended["state"] == "failed", ended
    assert "is full" in ended["message"], ended["message"]
    _tip_is_safe(server)
    full.clear()
    _wait("the failure recorded", lambda: server.services.runner.unrecorded(rid) is None)
    assert server.post(f"/api/runs/{rid}/resume").status_code == 202
    done = server.wait_state(rid, "completed", "failed", timeout=120)
    assert done["state"] == "completed" and done["progress"]["stored"] == done["progress"]["total"]


def test_a_resume_asked_while_the_failed_runs_worker_still_closes_waits_for_it(
    server: Server, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The failure recorded, the worker still closing the run (on a busy machine, seen in CI):
    a resume then waits for the worker and restarts the run, not 409 "running, not paused"."""
    import backend.acquisition.patch_loop as runner_module

    runner = server.services.runner
    full, closing = threading.Event(), threading.Event()
    real_write, real_record = runner_module.write_patch, runner._record

    def write_patch(*args: Any, **kwargs: Any) -> str:
        if full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(*args, **kwargs)

    def record(run_id: int, **kwargs: Any) -> bool:
        done = real_record(run_id, **kwargs)
        closing.wait(10)  # the worker lingers past its recorded end
        return done

    monkeypatch.setattr(runner_module, "write_patch", write_patch)
    monkeypatch.setattr(runner, "_record", record)
    rid = _start(server)
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2)
    full.set()
    assert server.wait_state(rid, "failed", "completed", timeout=120)["state"] == "failed"
    assert runner.active_run == rid  # its worker still closes it
    full.clear()
    monkeypatch.setattr(runner, "_record", real_record)
    threading.Timer(0.3, closing.set).start()
    assert server.post(f"/api/runs/{rid}/resume").status_code == 202
    assert server.wait_state(rid, "completed", "failed", timeout=120)["state"] == "completed"
