"""Every fault injected into the simulator ends in the safe state with a readable message."""

from __future__ import annotations

import time

import pytest

from tests.backend.api.conftest import Server, plan


def _tip_is_safe(server: Server) -> None:
    sim = server.services.microscope.sim
    assert sim is not None
    assert not sim.engaged(), "the force loop is still engaged"
    assert sim.robot_z.fine_extension() == pytest.approx(0.0, abs=1e-9)
    assert not sim.crashed


@pytest.mark.parametrize(
    ("fault", "words"),
    [
        ({"fault": "garbage", "link": "robot", "count": 3}, "positioner controller"),
        ({"fault": "error", "link": "robot", "count": 1, "code": 150}, "150"),
        ({"fault": "error", "link": "stage", "count": 1, "code": 157}, "157"),
        ({"fault": "silent", "link": "stage", "count": 3}, "no reply"),
        ({"fault": "no_surface"}, "no surface"),
    ],
)
def test_a_fault_fails_the_run_in_the_safe_state(
    server: Server, fault: dict[str, object], words: str
) -> None:
    run = server.create(plan(pixels=(12, 12)))
    rid = run["id"]
    r = server.post("/api/instrument/sim/fault", fault)
    assert r.status_code == 204, r.text
    server.post(f"/api/runs/{rid}/start")
    ended = server.wait_state(rid, "failed", "fault", "completed", timeout=120)
    assert ended["state"] == "failed", ended
    assert words in ended["message"], ended["message"]
    _tip_is_safe(server)
    patches = server.client.get(f"/api/runs/{rid}/patches").json()
    assert {p["step"] for p in patches} <= {"pending", "stored"}
    faults = server.client.get(f"/api/events?run_id={rid}&follow=false").text
    assert "event: fault" in faults
    # healed, the same run resumes from its first patch not stored and completes
    server.post("/api/instrument/sim/fault", {"fault": "none"})
    assert server.post(f"/api/runs/{rid}/resume").status_code == 202
    done = server.wait_state(rid, "completed", "failed", timeout=120)
    assert done["state"] == "completed", done
    assert done["progress"]["stored"] == done["progress"]["total"]


def test_a_link_that_stays_dead_blocks_the_instrument_until_reset(server: Server) -> None:
    run = server.create(plan(pixels=(12, 12)))
    rid = run["id"]
    server.post(f"/api/runs/{rid}/start")
    server.wait(rid, lambda r: r["progress"]["stored"] >= 1)
    server.post("/api/instrument/sim/fault", {"fault": "silent", "link": "robot"})
    ended = server.wait_state(rid, "fault", "failed", "completed", timeout=120)
    assert ended["state"] == "fault", ended
    assert "safe state not confirmed" in ended["message"]
    status = server.client.get("/api/instrument").json()
    assert status["state"] == "fault" and f"run {rid}" in status["message"]
    other = server.create()
    r = server.post(f"/api/runs/{other['id']}/start")
    assert r.status_code == 409 and "reset" in r.json()["detail"]
    assert server.post(f"/api/runs/{rid}/reset").status_code == 422  # a note is required
    checked = {"note": "robot link cable reseated"}
    r = server.post(f"/api/runs/{rid}/reset", checked)  # still dead: stays in fault
    assert r.status_code == 409 and "stays in fault" in r.json()["detail"]
    server.post("/api/instrument/sim/fault", {"fault": "none"})
    r = server.post(f"/api/runs/{rid}/reset", checked)
    assert r.status_code == 200, r.text
    assert r.json()["state"] == "failed" and "reset by the operator" in r.json()["message"]
    assert "robot link cable reseated" in r.json()["message"]
    _tip_is_safe(server)


def test_fault_injection_is_simulator_only_and_checked(server: Server) -> None:
    r = server.post("/api/instrument/sim/fault", {"fault": "melt"})
    assert r.status_code == 422
    r = server.post("/api/instrument/sim/fault", {"fault": "silent", "count": 0})
    assert r.status_code == 422
    r = server.client.post("/api/instrument/sim/fault", json={"fault": "none"})
    assert r.status_code == 401


def test_a_tip_left_down_with_no_run_is_withdrawn_by_the_supervisor(server: Server) -> None:
    sim = server.services.microscope.sim
    assert sim is not None
    sim.engage(10.0)  # as a worker that died mid-scan would leave it
    deadline = time.monotonic() + 10
    while sim.engaged():
        assert time.monotonic() < deadline, "the supervisor never withdrew the tip"
        time.sleep(0.05)
    _tip_is_safe(server)
