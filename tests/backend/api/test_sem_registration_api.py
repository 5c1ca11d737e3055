"""A merged mosaic registered onto an SEM image through the API, on the simulated SEM whose
rotation, scale and offset against the stage are hidden from the image's placement."""

from __future__ import annotations

import io
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hardware.sim.sem import SEMGeometry
from tests.backend.api.conftest import Server, open_server, plan

FIELD, PIXELS = 20e-6, 1024


@pytest.fixture(scope="module")
def merged(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Server, dict[str, Any]]]:
    """A 3 x 3 mosaic merged, and an SEM image taken before it (the stage at its origin)."""
    for server in open_server(tmp_path_factory.mktemp("registration")):
        image = server.post("/api/sem/acquire", {"field": FIELD, "pixels": PIXELS}).json()
        run = server.create(plan(size=2.6e-6, patch=1.2e-6, pixels=(64, 64)))
        server.post(f"/api/runs/{run['id']}/start")
        assert server.wait_state(run["id"], "completed", timeout=300)["state"] == "completed"
        job = server.post(f"/api/runs/{run['id']}/merges", {"method": "default"}).json()
        assert server.wait_merge(job["id"], timeout=300)["state"] == "done"
        yield server, {"sem": image, "merge": job["id"]}


def _truth(server: Server, sem: dict[str, Any], points: np.ndarray) -> np.ndarray:
    """Where the image, placed by its nominal pixel, shows stage points: through the
    simulator's true SEM map."""
    truth = server.client.get("/api/instrument/sim/sem").json()
    geometry = SEMGeometry(truth["rotation_deg"], truth["scale"], tuple(truth["offset"]))
    pixel = geometry.frame_pixels(points, field=FIELD, pixels=PIXELS)
    out: np.ndarray = pixel @ np.asarray(sem["matrix"]).T + np.asarray(sem["origin"])
    return out


def test_the_mosaic_is_registered_onto_the_sem_image_and_overlaid(
    merged: tuple[Server, dict[str, Any]],
) -> None:
    server, made = merged
    job, sem = made["merge"], made["sem"]
    r = server.post(f"/api/merges/{job}/sem-registration", {"sem": sem["id"]})
    assert r.status_code == 201, r.text
    found = r.json()
    assert found["accepted"], found["reason"]
    doc = server.client.get(f"/api/merges/{job}/mosaic.json").json()
    heights = np.load(io.BytesIO(server.client.get(f"/api/merges/{job}/mosaic.npy").content))
    (ox, oy), (px, py) = doc["origin"], doc["pixel_size"]
    ny, nx = heights.shape
    corners = np.array(
        [[ox, oy], [ox + nx * px, oy], [ox, oy + ny * py], [ox + nx * px, oy + ny * py]]
    )
    t = found["transform"]
    a = math.radians(t["rotation_deg"])
    turn = t["scale"] * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    placed = corners @ turn.T + np.asarray(t["offset"])
    misplaced = np.hypot(*(placed - _truth(server, sem, corners)).T) / (FIELD / PIXELS)
    assert misplaced.max() < 1.0, misplaced
    assert abs(t["rotation_deg"] + 3.0) < 0.1 and found["calibration"] is None
    assert server.client.get(f"/api/merges/{job}/sem-registration").json()["id"] == found["id"]
    png = server.client.get(f"/api/merges/{job}/sem-overlay.png", params={"opacity": 0.6})
    assert png.status_code == 200 and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert server.client.get(f"/api/merges/{job}/sem-overlay.png?opacity=2").status_code == 422


def test_registration_asks_for_what_exists(merged: tuple[Server, dict[str, Any]]) -> None:
    server, made = merged
    r = server.post(f"/api/merges/{made['merge']}/sem-registration", {"sem": 999})
    assert r.status_code == 404 and "GET /api/sem" in r.json()["detail"]
    r = server.post("/api/merges/999/sem-registration", {"sem": made["sem"]["id"]})
    assert r.status_code == 404
    r = server.post(f"/api/merges/{made['merge']}/sem-registration", {})
    assert r.status_code == 422 and "sem" in r.text
    r = server.client.post(f"/api/merges/{made['merge']}/sem-registration", json={"sem": 1})
    assert r.status_code == 401


def _registered(server: Server, job: int) -> dict[str, Any]:
    """A new SEM image (512 px: a quarter of the work) registered on merge ``job``: how far
    its calibration was off."""
    image = server.post("/api/sem/acquire", {"field": FIELD, "pixels": 512}).json()
    found = server.post(f"/api/merges/{job}/sem-registration", {"sem": image["id"]})
    assert found.status_code == 201 and found.json()["accepted"], found.text
    check: dict[str, Any] = found.json()["calibration"]
    assert check is not None and check["id"] == image["calibration_id"]
    return check


def test_a_registration_checks_the_calibration_and_corrects_one_that_is_off(
    tmp_path: Any,
) -> None:
    """With a good calibration in force, the registration finds the image placed within what
    the calibration stated. A calibration turned 0.4 degrees and 1 % off places an image a few
    pixels wrong where the mosaic lies: the registration measures it (beyond the stated
    uncertainty), its correction is applied, and the next image is placed within a pixel."""
    from backend.db.models import SemCalibrationRecord

    for server in open_server(tmp_path):
        good = server.post("/api/sem/calibrate", {"field": FIELD, "pixels": 256}).json()
        run = server.create(plan(size=2.6e-6, patch=1.2e-6, pixels=(64, 64)))
        server.post(f"/api/runs/{run['id']}/start")
        assert server.wait_state(run["id"], "completed", timeout=300)["state"] == "completed"
        job = server.post(f"/api/runs/{run['id']}/merges", {"method": "default"}).json()["id"]
        assert server.wait_merge(job, timeout=300)["state"] == "done"

        check = _registered(server, job)
        assert check["displacement_px"] <= check["stated_px"], check  # the good one
        with server.services.sessions() as session:
            record = session.get(SemCalibrationRecord, good["id"])
            assert record is not None
            a = math.radians(0.4)
            turn = 1.01 * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            columns = {c.name: getattr(record, c.name) for c in record.__table__.columns}
            skewed = (turn @ np.asarray(record.matrix)).tolist()
            session.add(SemCalibrationRecord(**{**columns, "id": None, "matrix": skewed}))
            session.commit()
        check = _registered(server, job)
        assert check["displacement_px"] > max(2.0, check["stated_px"]), check
        r = server.post(f"/api/merges/{job}/sem-registration/apply")
        assert r.status_code == 201, r.text
        assert r.json()["rotation_deg"] == pytest.approx(good["rotation_deg"], abs=0.05)
        assert _registered(server, job)["displacement_px"] < 1.0


def test_the_exports_keep_the_sem_image_beside_the_heights(
    merged: tuple[Server, dict[str, Any]], tmp_path: Path
) -> None:
    import tifffile

    from merge.io.formats.gwy import read_gwy

    server, made = merged
    job = made["merge"]
    r = server.post(f"/api/merges/{job}/sem-registration", {"sem": made["sem"]["id"]})
    assert r.json()["accepted"]
    doc = server.client.get(f"/api/merges/{job}/mosaic.json").json()
    assert doc["sem_registration"]["id"] == r.json()["id"]
    heights = np.load(io.BytesIO(server.client.get(f"/api/merges/{job}/mosaic.npy").content))
    gwy = tmp_path / "both.gwy"
    gwy.write_bytes(server.client.get(f"/api/merges/{job}/mosaic-sem.gwy").content)
    sem_channel = read_gwy(gwy, channel=f"SEM image {made['sem']['id']}")
    assert sem_channel.heights.shape == heights.shape
    assert np.isfinite(sem_channel.heights).all() and sem_channel.heights.std() > 0
    assert read_gwy(gwy).heights.shape == heights.shape  # the heights first
    tif = tmp_path / "both.tif"
    tif.write_bytes(server.client.get(f"/api/merges/{job}/mosaic-sem.tif").content)
    with tifffile.TiffFile(tif) as pages:
        assert len(pages.pages) == 2
        second = pages.pages[1].asarray()
    # the SEM page is the SEM signal where the mosaic lies: its bright fold crests sit on the
    # heights' slopes, so it correlates with the slope of the heights, not with nothing
    slope = np.hypot(*np.gradient(np.nan_to_num(heights)))[::-1]
    assert np.corrcoef(second.ravel(), slope.ravel())[0, 1] > 0.3
    r = server.client.get(f"/api/merges/{job}/mosaic-sem.png")
    assert r.status_code == 404 and ".gwy" in r.json()["detail"]


def test_a_profile_across_the_mosaic_gives_heights_and_sem_signal(
    merged: tuple[Server, dict[str, Any]],
) -> None:
    server, made = merged
    job = made["merge"]
    assert server.post(f"/api/merges/{job}/sem-registration", {"sem": made["sem"]["id"]}).json()[
        "accepted"
    ]
    doc = server.client.get(f"/api/merges/{job}/mosaic.json").json()
    (ox, oy), (px, py), (ny, nx) = doc["origin"], doc["pixel_size"], doc["shape"]
    line = {"x0": ox, "y0": oy + ny * py / 2, "x1": ox + nx * px * 1.5, "y1": oy + ny * py / 2}
    r = server.client.get(f"/api/merges/{job}/sem-profile", params={**line, "samples": 101})
    assert r.status_code == 200, r.text
    cut = r.json()
    assert len(cut["distance"]) == len(cut["height"]) == len(cut["sem"]) == 101
    assert cut["distance"][-1] == pytest.approx(nx * px * 1.5)
    heights = [h for h in cut["height"] if h is not None]
    assert 50 <= len(heights) <= 70 and max(heights) > min(heights)  # the mosaic's two thirds
    assert all(v is not None for v in cut["sem"])  # the SEM image reaches past the mosaic
    r = server.client.get(
        f"/api/merges/{job}/sem-profile", params={**line, "x1": ox, "y1": line["y0"]}
    )
    assert r.status_code == 422 and "distinct" in r.json()["detail"]


def test_the_overlay_states_where_its_pixels_lie_on_the_mosaic(
    merged: tuple[Server, dict[str, Any]],
) -> None:
    """A line drawn on the overlay picture becomes a line across the mosaic: the picture's
    pixels map to where the registration puts the mosaic (its centre comes out at the
    mosaic's centre), and the picture is as large as the box it states."""
    server, made = merged
    job = made["merge"]
    found = server.post(f"/api/merges/{job}/sem-registration", {"sem": made["sem"]["id"]}).json()
    frame = server.client.get(f"/api/merges/{job}/sem-overlay").json()
    assert frame["registration_id"] == found["id"] and frame["sem_id"] == made["sem"]["id"]
    png = server.client.get(f"/api/merges/{job}/sem-overlay.png").content
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    c0, r0, columns, rows = frame["box"]
    assert (width, height) == (columns, rows)
    doc = server.client.get(f"/api/merges/{job}/mosaic.json").json()
    (ox, oy), (px, py), (ny, nx) = doc["origin"], doc["pixel_size"], doc["shape"]
    middle = np.array([ox + (nx - 1) * px / 2, oy + (ny - 1) * py / 2])
    t = found["transform"]
    a = math.radians(t["rotation_deg"])
    turn = t["scale"] * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    sem = made["sem"]
    shown = np.linalg.solve(
        np.asarray(sem["matrix"]), turn @ middle + np.asarray(t["offset"]) - sem["origin"]
    )  # the SEM pixel that shows the mosaic's centre
    m = np.asarray(frame["pixel_to_mosaic"])
    back = m @ np.array([shown[0] - c0, shown[1] - r0, 1.0])
    assert np.hypot(*(back - middle)) < 1e-12
