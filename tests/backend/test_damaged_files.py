"""Start-up with damaged files: a damaged run is set aside, a damaged database is named."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.backend.api.conftest import open_server, plan


def test_a_run_file_that_cannot_be_opened_is_quarantined_and_the_server_starts(
    tmp_path: Path,
) -> None:
    for server in open_server(tmp_path):
        run = server.create(plan(pixels=(12, 12)))
        server.post(f"/api/runs/{run['id']}/start")
        assert server.wait_state(run["id"], "completed", "failed")["state"] == "completed"
    path = tmp_path / "runs" / f"run-{run['id']:05d}.h5"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])  # truncated
    for server in open_server(tmp_path):
        damaged = server.client.get(f"/api/runs/{run['id']}").json()
        assert damaged["state"] == "damaged", damaged
        assert "could not be opened" in damaged["message"] and "quarantine" in damaged["message"]
        assert not path.exists() and len(list((tmp_path / "quarantine").iterdir())) == 1
        r = server.post(f"/api/runs/{run['id']}/start")
        assert r.status_code == 409, r.text  # damaged is final
        other = server.create(plan(pixels=(12, 12)))
        server.post(f"/api/runs/{other['id']}/start")
        assert server.wait_state(other["id"], "completed", "failed")["state"] == "completed"


def test_a_damaged_database_names_the_file_and_the_way_back(tmp_path: Path) -> None:
    (tmp_path / "mosaic.sqlite").write_bytes(b"this is not a database, it was overwritten" * 50)
    done = subprocess.run(
        [sys.executable, "-m", "backend.cli", "serve", "--data-dir", str(tmp_path), "--port", "1"],
        capture_output=True,
        text=True,
        timeout=60,
        env={"MOSAIC_VIEWER": "false", "PATH": "/usr/bin:/bin"},
        check=False,
    )
    assert done.returncode == 2, done.stderr
    assert "mosaic.sqlite is damaged" in done.stderr, done.stderr
    assert ".recover" in done.stderr and "mosaic-afm backup" in done.stderr
    assert "Traceback" not in done.stderr
