"""The server as a process: a whole mosaic scored against the truth, and a SIGKILL mid-run."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from backend.server_process import AUTH, ServerProcess, wait_for
from merge.report.evaluate import Grid, score_mosaic

#: The paper's grid: 5 x 10 patches of 0.6 x 1.2 µm, 50 % / 33 % overlap, 20 nm pixels.
PAPER_GRID = {
    "roi": {"x": -1.65e-6, "y": -2.2e-6, "width": 3.3e-6, "height": 4.4e-6},
    "patch": {"width": 0.6e-6, "height": 1.2e-6, "pixels": [30, 60]},
    "overlap": [0.5, 1 / 3],
}


def _score(client: object, job: dict[str, object], margin: float = 0.3e-6) -> object:
    import httpx

    assert isinstance(client, httpx.Client)
    heights = np.load(io.BytesIO(client.get(str(job["mosaic_npy"])).content))
    doc = client.get(str(job["mosaic_json"])).json()
    (ox, oy), (px, py) = doc["origin"], doc["pixel_size"]
    ny, nx = heights.shape
    pitch = 10e-9
    truth = client.get(
        "/api/instrument/sim/surface",
        params={
            "x": ox - margin,
            "y": oy - margin,
            "width": nx * px + 2 * margin,
            "height": ny * py + 2 * margin,
            "pixel": pitch,
            "tip": "true",
        },
    )
    assert truth.status_code == 200, truth.text
    reference = Grid(np.load(io.BytesIO(truth.content)), (ox - margin, oy - margin), (pitch,) * 2)
    return score_mosaic(Grid(heights, (ox, oy), (px, py)), reference, tile=(0.6e-6, 0.6e-6))


@pytest.mark.slow
def test_a_5_x_10_mosaic_over_http_merges_close_to_the_truth(tmp_path: Path) -> None:
    # the merge's accuracy over HTTP: no live merge beside the scan (the page tests run the
    # server as it starts by default, live merge included, on mosaics of their own)
    server = ServerProcess(tmp_path, MOSAIC_AUTO_MERGE="true", MOSAIC_LIVE_MERGE="false").start()
    try:
        with server.client() as client:
            run = client.post("/api/runs", json=PAPER_GRID, headers=AUTH).json()
            assert (run["rows"], run["cols"]) == (5, 10)
            client.post(f"/api/runs/{run['id']}/start", headers=AUTH)
            done = wait_for(
                client,
                f"/api/runs/{run['id']}",
                lambda r: r["state"] == "completed" and r["merges"],
            )
            job = wait_for(
                client,
                f"/api/merges/{done['merges'][0]}",
                lambda j: j["state"] in ("done", "failed", "cancelled"),
            )
            assert job["state"] == "done", job
            merged = _score(client, job)
            nominal = client.post(
                f"/api/runs/{run['id']}/merges", json={"method": "nominal"}, headers=AUTH
            ).json()
            nominal = wait_for(
                client, f"/api/merges/{nominal['id']}", lambda j: j["state"] == "done"
            )
            placed = _score(client, nominal)
    finally:
        server.stop()
    # local registration (tile by tile, after one global rigid motion and plane)
    assert merged.tile_xy_rms < 2.0e-9  # type: ignore[attr-defined]
    assert merged.tile_z_rms < 1.5e-9  # type: ignore[attr-defined]
    assert merged.map_rms < 0.3 * placed.map_rms  # type: ignore[attr-defined]
    assert merged.tile_xy_rms < 0.2 * placed.tile_xy_rms  # type: ignore[attr-defined]


@pytest.mark.slow
def test_sigkill_mid_run_then_resume_stores_every_patch_exactly_once(tmp_path: Path) -> None:
    plan = {
        "roi": {"x": -1.5e-6, "y": -1.5e-6, "width": 3e-6, "height": 3e-6},  # 4 x 4 patches
        "patch": {"width": 1e-6, "height": 1e-6, "pixels": [40, 40]},
        "overlap": [0.2, 0.2],
    }
    first = ServerProcess(tmp_path, MOSAIC_AUTO_MERGE="false").start()
    with first.client() as client:
        run = client.post("/api/runs", json=plan, headers=AUTH).json()
        rid, total = run["id"], run["progress"]["total"]
        client.post(f"/api/runs/{rid}/start", headers=AUTH)
        wait_for(client, f"/api/runs/{rid}", lambda r: r["progress"]["stored"] >= 3, poll=0.005)
    first.kill()
    second = ServerProcess(tmp_path, port=first.port, MOSAIC_AUTO_MERGE="false").start()
    try:
        with second.client() as client:
            after = client.get(f"/api/runs/{rid}").json()
            assert after["state"] == "interrupted"
            assert 3 <= after["progress"]["stored"] < total
            assert {p["step"] for p in client.get(f"/api/runs/{rid}/patches").json()} <= {
                "pending",
                "stored",
            }
            r = client.post(f"/api/runs/{rid}/resume", headers=AUTH)
            assert r.status_code == 202, r.text
            done = wait_for(client, f"/api/runs/{rid}", lambda b: b["state"] != "running")
            assert done["state"] == "completed", done
            assert done["progress"]["stored"] == total
            for index in range(total):
                r = client.get(f"/api/runs/{rid}/patches/{index}/data")
                assert r.status_code == 200
                assert np.isfinite(np.load(io.BytesIO(r.content))).all()
    finally:
        second.stop()
    # exactly once: one complete dataset per patch in the run's file (a patch cut short by
    # the kill was scanned again, its half-written data removed or its finished data adopted)
    with h5py.File(tmp_path / "runs" / f"run-{rid:05d}.h5", "r") as f:
        names = sorted(f["patches"])
        assert names == [f"{i:05d}" for i in range(total)]
        assert all(f["patches"][n].attrs["complete"] for n in names)


@pytest.mark.slow
def test_sigkill_of_the_server_mid_merge_takes_its_worker_along(tmp_path: Path) -> None:
    # the run only makes the patches to merge: no live merge beside it (a core's worth of load
    # on the suite's other worker for nothing this test checks)
    server = ServerProcess(tmp_path, MOSAIC_AUTO_MERGE="false", MOSAIC_LIVE_MERGE="false").start()
    pid_file = tmp_path / "merge-worker.pid"
    try:
        with server.client() as client:
            run = client.post("/api/runs", json=PAPER_GRID, headers=AUTH).json()
            client.post(f"/api/runs/{run['id']}/start", headers=AUTH)
            wait_for(client, f"/api/runs/{run['id']}", lambda r: r["state"] == "completed")
            r = client.post(f"/api/runs/{run['id']}/merges", json={}, headers=AUTH)
            assert r.status_code == 202, r.text
            deadline = time.monotonic() + 60
            while not pid_file.exists():
                assert time.monotonic() < deadline, "the merge worker never started"
                time.sleep(0.01)
            worker = int(pid_file.read_text())
    finally:
        server.kill()
    deadline = time.monotonic() + 10
    while Path(f"/proc/{worker}").exists() and b"Z" not in _state(worker):
        assert time.monotonic() < deadline, f"merge worker {worker} outlived the server"
        time.sleep(0.05)


def _state(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/stat").read_bytes().split(b") ")[1][:1]
    except (OSError, IndexError):
        return b"Z"


def test_start_up_reaps_a_worker_a_previous_server_left(tmp_path: Path) -> None:
    from backend.merge_worker import PID_FILE, reap_leftover

    leftover = subprocess.Popen(
        [sys.executable, "-c", "import multiprocessing, time; time.sleep(120)"]
    )
    try:
        cmdline = Path(f"/proc/{leftover.pid}/cmdline")
        deadline = time.monotonic() + 10
        while b"multiprocessing" not in cmdline.read_bytes():  # it runs its command
            assert time.monotonic() < deadline
            time.sleep(0.01)
        (tmp_path / PID_FILE).write_text(f"{leftover.pid}\n")
        note = reap_leftover(tmp_path)
        assert note is not None and note.startswith(f"killed merge worker {leftover.pid}"), note
        assert leftover.wait(10) == -9
        assert not (tmp_path / PID_FILE).exists()
        (tmp_path / PID_FILE).write_text(f"{os.getpid()}\n")  # never this process itself
        assert "left alone" in str(reap_leftover(tmp_path))
        assert reap_leftover(tmp_path) is None  # the pid file is gone
    finally:
        if leftover.poll() is None:
            leftover.kill()


def test_a_port_taken_before_the_bind_is_given_up_for_another(tmp_path: Path) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        server = ServerProcess(tmp_path)
        server.port = taken.getsockname()[1]  # as if another process got there first
        server.start()
        try:
            assert server.port != taken.getsockname()[1]
            with server.client() as client:
                assert client.get("/api/instrument").status_code == 200
        finally:
            server.stop()


def test_a_port_asked_for_and_taken_is_an_error(tmp_path: Path) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        server = ServerProcess(tmp_path, port=taken.getsockname()[1])
        with pytest.raises(RuntimeError, match="address already in use"):
            server.start()
