"""Merge jobs through the API: queue, follow, cancel, download."""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.backend.api.conftest import Server, open_server, plan


@pytest.fixture(scope="module")
def scanned(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, int]]:
    """One server with a completed 3 x 3 run, shared by the tests of this module."""
    for server in open_server(Path(tmp_path_factory.mktemp("merges"))):
        run = server.create(plan(pixels=(32, 32)))
        server.post(f"/api/runs/{run['id']}/start")
        server.wait_state(run["id"], "completed")
        yield server, run["id"]


def test_a_merge_runs_in_its_process_and_serves_the_result_contract(
    scanned: tuple[Server, int],
) -> None:
    server, rid = scanned
    r = server.post(f"/api/runs/{rid}/merges", {"method": "default"})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] in ("queued", "running") and job["patches"] == list(range(9))
    early = server.client.get(f"/api/merges/{job['id']}/mosaic.npy")
    assert early.status_code in (200, 404)
    done = server.wait_merge(job["id"])
    assert done["state"] == "done", done
    assert done["progress"] == 1.0 and done["iteration"] > 0 and done["residual"] < 5e-9
    heights = np.load(io.BytesIO(server.client.get(done["mosaic_npy"]).content))
    doc = server.client.get(done["mosaic_json"]).json()
    assert list(heights.shape) == doc["shape"]
    assert np.isfinite(heights).mean() > 0.9
    # sim:// rows are placed by the Y sensor: no self-calibration unless asked for
    assert doc["parameters"]["self_calibrate"] is False and "scan_distortion" not in doc
    assert [p["id"] for p in doc["patches"]] == [f"p{i:03d}" for i in range(9)]
    assert all(np.asarray(p["rotation"]).shape == (3, 3) for p in doc["patches"])
    events = server.client.get(f"/api/events?run_id={rid}&follow=false").text
    assert "iteration" in events and "done" in events
    listed = server.client.get(f"/api/runs/{rid}/merges").json()
    assert job["id"] in [j["id"] for j in listed]
    assert job["id"] in server.client.get(f"/api/runs/{rid}").json()["merges"]


def test_a_subset_and_another_method(scanned: tuple[Server, int]) -> None:
    server, rid = scanned
    r = server.post(
        f"/api/runs/{rid}/merges",
        {
            "method": "zlevel",
            "patches": [0, 1, 2],
            "parameters": {"feather": 0.1, "coarse_cell": 3e-8},
        },
    )
    assert r.status_code == 202, r.text
    done = server.wait_merge(r.json()["id"])
    assert done["state"] == "done" and done["patches"] == [0, 1, 2]
    doc = server.client.get(done["mosaic_json"]).json()
    assert doc["method"] == "zlevel" and len(doc["patches"]) == 3
    assert doc["parameters"]["coarse_cell"] == 3e-8


def test_self_calibration_when_asked_for(scanned: tuple[Server, int]) -> None:
    server, rid = scanned
    r = server.post(f"/api/runs/{rid}/merges", {"parameters": {"self_calibrate": True}})
    assert r.status_code == 202, r.text
    done = server.wait_merge(r.json()["id"])
    assert done["state"] == "done", done
    doc = server.client.get(done["mosaic_json"]).json()
    assert doc["parameters"]["self_calibrate"] is True
    bend = doc["scan_distortion"]
    assert len(bend["rows"]) == 32 and len(bend["cols"]) == 32
    # the sensor straightened the rows already: what is left is within the noise
    assert max(map(abs, bend["rows"])) < 1e-9, bend["peak_to_valley"]


@pytest.mark.parametrize(
    ("body", "status", "words"),
    [
        ({"method": "magic"}, 422, "method"),
        ({"parameters": {"max_iter": 0}}, 422, "max_iter"),
        ({"parameters": {"cell": -1}}, 422, "cell"),
        ({"parameters": {"coarse_cell": 0}}, 422, "coarse_cell"),
        ({"parameters": {"colour": "red"}}, 422, "colour"),
        ({"method": "nominal", "parameters": {"self_calibrate": True}}, 422, "default method"),
        ({"patches": [0, 99]}, 409, "not stored"),
        ({"patches": [4]}, 409, "at least 2"),
    ],
)
def test_bad_merge_requests_say_what_to_fix(
    scanned: tuple[Server, int], body: dict[str, object], status: int, words: str
) -> None:
    server, rid = scanned
    r = server.post(f"/api/runs/{rid}/merges", body)
    assert r.status_code == status, r.text
    assert words in r.text


def test_cancel_a_queued_or_running_merge(scanned: tuple[Server, int]) -> None:
    server, rid = scanned
    first = server.post(f"/api/runs/{rid}/merges", {"method": "paper"}).json()
    second = server.post(f"/api/runs/{rid}/merges", {}).json()
    r = server.post(f"/api/merges/{second['id']}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "cancelled"
    server.post(f"/api/merges/{first['id']}/cancel")
    ended = server.wait_merge(first["id"])
    assert ended["state"] in ("cancelled", "done")
    again = server.post(f"/api/merges/{second['id']}/cancel")
    assert again.status_code == 409 and "already cancelled" in again.json()["detail"]
    r = server.client.get(f"/api/merges/{second['id']}/mosaic.npy")
    assert r.status_code == 404 and "cancelled" in r.json()["detail"]


def test_merges_of_nothing_are_404(scanned: tuple[Server, int]) -> None:
    server, _ = scanned
    assert server.client.get("/api/merges/999").status_code == 404
    assert server.post("/api/runs/999/merges", {}).status_code == 404
    assert server.post("/api/merges/999/cancel").status_code == 404
