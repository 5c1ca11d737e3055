"""``check`` finds what does not agree; ``backup`` taken mid-run restores to a server that
resumes the run."""

from __future__ import annotations

from pathlib import Path

import h5py

from backend.cli import main
from backend.db.maintenance import backup_data_dir, check_data_dir
from tests.backend.api.conftest import open_server, plan


def test_check_passes_a_healthy_directory_and_names_what_is_wrong(tmp_path: Path) -> None:
    for server in open_server(tmp_path):
        run = server.create(plan(pixels=(12, 12)))
        server.post(f"/api/runs/{run['id']}/start")
        assert server.wait_state(run["id"], "completed")["state"] == "completed"
        job = server.post(f"/api/runs/{run['id']}/merges", {}).json()
        assert server.wait_merge(job["id"])["state"] == "done"
    report = check_data_dir(tmp_path)
    assert report.ok, report.problems
    assert main(["check", "--data-dir", str(tmp_path)]) == 0
    with h5py.File(tmp_path / "runs" / f"run-{run['id']:05d}.h5", "a") as f:
        del f["patches/00003"]
    report = check_data_dir(tmp_path)
    assert any("patch 3 is stored in the database" in p for p in report.problems)
    assert main(["check", "--data-dir", str(tmp_path)]) == 1
    assert main(["check", "--data-dir", str(tmp_path / "nowhere")]) == 2


def test_a_backup_taken_mid_run_restores_to_a_server_that_resumes_it(tmp_path: Path) -> None:
    live, copy = tmp_path / "live", tmp_path / "copy"
    big = plan(size=4e-6, patch=1e-6, pixels=(32, 32))
    for server in open_server(live):
        run = server.create(big)
        rid, total = run["id"], run["progress"]["total"]
        server.post(f"/api/runs/{rid}/start")
        server.wait(rid, lambda r: r["progress"]["stored"] >= 2)
        backup_data_dir(live, copy)  # while the server scans
        server.wait_state(rid, "completed", "failed")
    assert main(["backup", str(copy), "--data-dir", str(live)]) == 2  # not an empty folder
    for server in open_server(copy):
        restored = server.client.get(f"/api/runs/{rid}").json()
        assert restored["state"] == "interrupted", restored
        assert 2 <= restored["progress"]["stored"] < total
        assert server.post(f"/api/runs/{rid}/resume").status_code == 202
        done = server.wait_state(rid, "completed", "failed", timeout=120)
        assert done["state"] == "completed" and done["progress"]["stored"] == total
    assert check_data_dir(copy).ok
