"""Live merge and re-scans over HTTP on the simulated instrument: a spoiled patch is found by
the quality gate and scanned again, one that cannot be mended is flagged and left out, and the
live mosaic is there while the run goes on and after it ends."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.backend.api.conftest import Server, open_server, plan


@pytest.fixture
def merging(tmp_path: Path) -> Iterator[Server]:
    yield from open_server(tmp_path, auto_merge=True, live_merge=True)


def _mosaic_plan(**extra: Any) -> dict[str, Any]:
    # 4 x 4 patches of 32 x 32 px at 30 % overlap: enough overlap for the gate to judge by
    return plan(size=2.0e-6, patch=0.8e-6, pixels=(32, 32), overlap=(0.3, 0.3), **extra)


def _run(server: Server, body: dict[str, Any]) -> dict[str, Any]:
    run = server.create(body)
    assert server.post(f"/api/runs/{run['id']}/start").status_code == 202
    done = server.wait_state(run["id"], "completed", "failed", timeout=240)
    assert done["state"] == "completed", done["message"]
    return done


def test_a_spoiled_patch_is_scanned_again_and_the_live_mosaic_holds_every_patch(
    merging: Server,
) -> None:
    fault = {"fault": "z_jump", "patches": [4], "count": 1}
    assert merging.post("/api/instrument/sim/fault", fault).status_code == 204
    run = _run(merging, _mosaic_plan())
    rid = run["id"]
    # patch 4's spoiled lines may have had no neighbour when it was stored: then the next
    # patch over them is blamed first, and its re-scan, lying as badly, turns the blame on 4
    rescans = [(r["index"], r["try"]) for r in run["rescans"]]
    assert (4, 2) in rescans and len(rescans) <= 2
    reason = next(r["reason"] for r in run["rescans"] if r["index"] == 4)
    assert "Z step" in reason or "residual" in reason
    patches = {p["index"]: p for p in merging.client.get(f"/api/runs/{rid}/patches").json()}
    assert patches[4]["quality"] == "rescanned" and patches[4]["tries"] == 2
    rescanned = {i for i, _ in rescans}
    others = {i: p["quality"] for i, p in patches.items() if i not in rescanned}
    assert set(others.values()) == {"ok"}, others
    doc = merging.client.get(f"/api/runs/{rid}/live/mosaic.json").json()
    total = run["progress"]["total"]
    assert doc["patches_merged"] == total and doc["units"] == "m" and doc["live"] is True
    heights = np.load(
        __import__("io").BytesIO(merging.client.get(f"/api/runs/{rid}/live/mosaic.npy").content)
    )
    assert list(heights.shape) == doc["shape"] and np.isfinite(heights).mean() > 0.8
    job = merging.wait_merge(run["merges"][0] if run["merges"] else _first_merge(merging, rid))
    assert job["state"] == "done" and job["patches"] == list(range(total))


def test_a_patch_spoiled_every_try_is_flagged_and_left_out_of_the_merge(merging: Server) -> None:
    fault = {"fault": "parachute", "patches": [4]}
    assert merging.post("/api/instrument/sim/fault", fault).status_code == 204
    run = _run(merging, _mosaic_plan(rescan={"enabled": True, "max_tries": 2}))
    rid = run["id"]
    assert (4, 2) in [(r["index"], r["try"]) for r in run["rescans"]]
    patches = {p["index"]: p for p in merging.client.get(f"/api/runs/{rid}/patches").json()}
    assert patches[4]["quality"] == "flagged" and patches[4]["tries"] == 2
    assert patches[4]["reason"]
    assert all(p["quality"] != "flagged" for i, p in patches.items() if i != 4)
    job = merging.wait_merge(_first_merge(merging, rid))
    total = run["progress"]["total"]
    assert job["state"] == "done" and job["patches"] == [i for i in range(total) if i != 4]
    doc = merging.client.get(f"/api/runs/{rid}/live/mosaic.json").json()
    assert doc["patches_merged"] == total - 1


def test_scans_failing_their_own_record_in_a_row_stop_the_run(merging: Server) -> None:
    """Lines lost on every patch from 4 on is the instrument, not one patch: three such
    scans in a row fail the run, in the safe state, saying why."""
    fault = {"fault": "lost_lines", "patches": [4, 5, 6, 7]}
    assert merging.post("/api/instrument/sim/fault", fault).status_code == 204
    run = merging.create(_mosaic_plan(rescan={"enabled": True, "max_tries": 2}))
    assert merging.post(f"/api/runs/{run['id']}/start").status_code == 202
    done = merging.wait_state(run["id"], "completed", "failed", "fault", timeout=240)
    assert done["state"] == "failed", done
    assert "3 scans in a row failed their own record" in done["message"], done["message"]
    assert "lines lost" in done["message"]
    assert [r["index"] for r in done["rescans"]] == [4]
    assert not merging.client.get("/api/instrument").json()["loop_engaged"]


def _first_merge(server: Server, run_id: int) -> int:
    run = server.wait(run_id, lambda r: bool(r["merges"]), timeout=30)
    merges: list[int] = run["merges"]
    return merges[0]


def test_live_mosaic_and_rescan_requests_say_what_is_wrong(server: Server) -> None:
    run = server.create(_mosaic_plan())
    r = server.client.get(f"/api/runs/{run['id']}/live/mosaic.npy")
    assert r.status_code == 404 and "no live mosaic yet" in r.json()["detail"]
    r = server.post(f"/api/runs/{run['id']}/patches/0/rescan")
    assert r.status_code == 409 and "not running" in r.json()["detail"]
    r = server.post("/api/instrument/sim/fault", {"fault": "tip_change"})
    assert r.status_code == 422 and "give patches" in r.text
    r = server.post("/api/instrument/sim/fault", {"fault": "silent", "patches": [1]})
    assert r.status_code == 422 and "drop patches" in r.text
    r = server.post("/api/runs", _mosaic_plan(rescan={"enabled": True, "max_tries": 0}))
    assert r.status_code == 422 and "max_tries" in r.text
