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


def _feature(server: Server, sem_id: int) -> tuple[float, float]:
    """The brightest blob (a fold crest, bright in secondary electrons) in the image's upper
    right, well off its centre: column, row."""
    import io

    from scipy import ndimage

    pixels = np.load(io.BytesIO(server.client.get(f"/api/sem/{sem_id}/image.npy").content))
    smooth = ndimage.gaussian_filter(pixels, 3.0)
    corner = smooth[24:96, 160:232]
    r, c = np.unravel_index(int(np.argmax(corner)), corner.shape)
    return float(c + 160), float(r + 24)


def _truly_at(truth: dict[str, object], column: float, row: float, pitch: float) -> np.ndarray:
    """Where SEM pixel (column, row) of a frame of ``pitch`` (256 px, no scan rotation, the
    stage at 0) truly is on the stage."""
    a = np.deg2rad(float(truth["rotation_deg"]))  # type: ignore[arg-type]
    scale = float(truth["scale"])  # type: ignore[arg-type]
    u, v = (column - 127.5) * pitch, -(row - 127.5) * pitch
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.asarray(truth["offset"]) + scale * rot @ np.array([u, v])


def test_an_roi_drawn_around_a_feature_lands_on_it_only_through_the_calibration(
    turned: Server,
) -> None:
    """The issue's check: an ROI drawn around a feature of the SEM image, planned, holds the
    feature where it was drawn (within 2 % of the ROI's size) once the SEM is calibrated;
    placed by its nominal pixel size alone (3 degrees and 2.5 % off), it does not."""
    server, field, side = turned, 20e-6, 32  # an ROI of 32 px: 2.5 µm
    pitch = field / 256
    misses = {}
    for calibrated in (False, True):
        if calibrated:
            assert server.post("/api/sem/calibrate", {"field": field}).status_code == 201
        image = server.post("/api/sem/acquire", {"field": field, "pixels": 256}).json()
        truth = server.client.get("/api/instrument/sim/sem").json()  # as this frame saw it
        column, row = _feature(server, image["id"])
        drawn = {"col": column - side / 2, "row": row - side / 2, "width": side, "height": side}
        body = plan(patch=1e-6, pixels=(32, 32))
        body.pop("roi")
        r = server.post("/api/runs/preview", {**body, "sem_roi": {"sem_id": image["id"], **drawn}})
        assert r.status_code == 200, r.text
        roi = r.json()["roi"]
        centre = np.array([roi["x"] + roi["width"] / 2, roi["y"] + roi["height"] / 2])
        size = side * pitch * SCALE
        misses[calibrated] = np.hypot(*(centre - _truly_at(truth, column, row, pitch))) / size
    assert misses[True] < 0.02, misses
    assert misses[False] > 0.05, misses


def test_the_calibrations_are_listed_newest_first(turned: Server) -> None:
    server = turned
    assert server.client.get("/api/sem/calibrations").json() == []
    quick = {"field": 20e-6, "pixels": 128}  # coarse frames: only the records matter here
    ids = [server.post("/api/sem/calibrate", quick).json()["id"] for _ in range(2)]
    listed = server.client.get("/api/sem/calibrations").json()
    assert [c["id"] for c in listed] == ids[::-1]
    assert server.client.get("/api/sem/calibration").json()["id"] == ids[-1]


def test_a_frame_is_placed_by_the_calibration_nearest_its_field(turned: Server) -> None:
    server = turned
    wide = server.post("/api/sem/calibrate", {"field": 30e-6, "pixels": 128}).json()["id"]
    narrow = server.post("/api/sem/calibrate", {"field": 12e-6, "pixels": 128}).json()["id"]
    near = server.client.get("/api/sem/calibration", params={"field": 40e-6}).json()
    assert near["id"] == wide
    assert server.client.get("/api/sem/calibration").json()["id"] == narrow
    image = server.post("/api/sem/acquire", {"field": 40e-6, "pixels": 64}).json()
    assert image["calibration_id"] == wide
    image = server.post("/api/sem/acquire", {"field": 200e-6, "pixels": 64}).json()
    assert image["calibration_id"] == narrow  # none near: the newest
