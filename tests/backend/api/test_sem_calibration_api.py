"""The SEM-to-stage calibration through the API, on the simulated SEM rotated and scaled
against the stage: measured, stored, in force for the frames acquired after it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tests.backend.api.conftest import Server, open_server, plan

#: The simulated SEM's scan against the stage (as the stage's sensors read it).
ROTATION, SCALE = 3.0, 1.025


@pytest.fixture
def turned(tmp_path: Path) -> Iterator[Server]:
    yield from open_server(
        tmp_path, instrument=f"sim://?speed=max&sem_rotation={ROTATION}&sem_scale={SCALE}"
    )


def test_the_calibration_finds_the_sems_rotation_and_scale_and_places_frames(
    turned: Server,
) -> None:
    server = turned
    assert server.client.get("/api/sem/calibration").status_code == 404
    r = server.post("/api/sem/calibrate", {"field": 20e-6, "pixels": 256})
    assert r.status_code == 201, r.text
    found = r.json()
    pitch = 20e-6 / 256
    truth = server.client.get("/api/instrument/sim/sem").json()
    assert (truth["rotation_deg"], truth["scale"]) == (ROTATION, SCALE)
    # the bounds: rotation within 0.05 degrees, scale within 0.1 %, offset a pixel
    assert found["rotation_deg"] == pytest.approx(ROTATION, abs=0.05)
    for scale in found["scale"]:
        assert scale / pitch == pytest.approx(SCALE, rel=1e-3)
    assert np.hypot(*np.subtract(found["offset"], truth["offset"])) < SCALE * pitch
    assert abs(found["shear"]) < 2e-3 and found["residual_px"] < 0.5
    assert len(found["moves"]) == 24 and found["actor"] == "tester"
    assert server.client.get("/api/sem/calibration").json()["id"] == found["id"]
    sim = server.services.microscope.sim
    assert sim is not None and np.hypot(*sim.stage_position()) < 1e-8  # back where it began
    # a frame taken now is placed through it: turned by its rotation, rows down the screen
    image = server.post("/api/sem/acquire", {"field": 10e-6, "pixels": 256}).json()  # half a pixel
    (a, b), (c, d) = image["matrix"]
    assert np.degrees(np.arctan2(c, a)) == pytest.approx(found["rotation_deg"], abs=1e-9)
    assert a * d - b * c < 0 and np.hypot(a, c) == pytest.approx(found["scale"][0] / 2)


def test_a_calibration_waits_for_no_run_and_a_field_without_texture_is_refused(
    turned: Server,
) -> None:
    server = turned
    run = server.create(plan(size=2.5e-6, pixels=(48, 48)))
    server.post(f"/api/runs/{run['id']}/start")
    r = server.post("/api/sem/calibrate", {"field": 20e-6})
    assert r.status_code == 409 and "using the instrument" in r.json()["detail"]
    server.wait_state(run["id"], "completed")
    r = server.post("/api/sem/calibrate", {"field": 20e-6, "step": 20e-9})  # a quarter pixel
    assert r.status_code == 422 and "did not move" in r.json()["detail"]
