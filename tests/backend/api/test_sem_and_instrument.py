"""SEM images (acquired, uploaded TIFFs), ROIs drawn on them, the instrument's state and truth."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
import tifffile

from tests.backend.api.conftest import AUTH, Server


def _tiff(pixels: np.ndarray, *, fei_pixel: float | None = None) -> bytes:
    buffer = io.BytesIO()
    extratags = []
    if fei_pixel is not None:
        text = f"[User]\nDate=11/23/2026\n[Scan]\nPixelWidth={fei_pixel}\nPixelHeight={fei_pixel}\n"
        extratags.append((34682, "s", 0, text, True))
    tifffile.imwrite(buffer, pixels, extratags=extratags)
    return buffer.getvalue()


def _upload(server: Server, data: bytes, **form: str) -> httpx.Response:
    return server.client.post(
        "/api/sem/upload",
        headers=AUTH,
        files={"file": ("image.tif", data, "image/tiff")},
        data=form,
    )


def test_acquire_an_sem_image_and_plan_on_its_pixels(server: Server) -> None:
    r = server.post("/api/sem/acquire", {"centre": [0, 0], "field": 8e-6, "pixels": 128})
    assert r.status_code == 201, r.text
    sem = r.json()
    assert sem["pixel_size"] == pytest.approx([8e-6 / 128] * 2)
    pixels = np.load(io.BytesIO(server.client.get(f"/api/sem/{sem['id']}/image.npy").content))
    assert pixels.shape == (128, 128) and pixels.std() > 0
    # a 32 x 32 px rectangle in the middle is 2 x 2 µm around the origin
    body = {
        "sem_roi": {"sem_id": sem["id"], "col": 48, "row": 48, "width": 32, "height": 32},
        "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [16, 16]},
        "overlap": [0.25, 0.25],
    }
    run = server.post("/api/runs", body).json()
    assert run["roi"]["width"] == pytest.approx(2e-6)
    assert run["roi"]["x"] + run["roi"]["width"] / 2 == pytest.approx(0, abs=0.07e-6)
    outside = {**body, "sem_roi": {**body["sem_roi"], "col": 120}}
    r = server.post("/api/runs", outside)
    assert r.status_code == 422 and "leaves" in r.json()["detail"]
    missing = {**body, "sem_roi": {**body["sem_roi"], "sem_id": 99}}
    assert server.post("/api/runs", missing).status_code == 404


def test_upload_reads_the_vendor_pixel_size(server: Server) -> None:
    image = (np.arange(64 * 48).reshape(48, 64) % 251).astype(np.uint8)
    r = _upload(server, _tiff(image, fei_pixel=12.5e-9), origin_x="1e-6")
    assert r.status_code == 201, r.text
    sem = r.json()
    assert sem["pixel_size"] == pytest.approx([12.5e-9, 12.5e-9])
    assert (sem["width"], sem["height"]) == (64, 48) and sem["origin"][0] == 1e-6
    assert "FEI" in sem["source"]


def test_upload_without_vendor_tags_needs_the_pixel_size(server: Server) -> None:
    data = _tiff(np.zeros((32, 32), dtype=np.uint16))
    r = _upload(server, data)
    assert r.status_code == 422 and "pixel_size" in r.json()["detail"]
    r = _upload(server, data, pixel_size="5e-9")
    assert r.status_code == 201 and r.json()["pixel_size"] == [5e-9, 5e-9]


def test_bad_uploads_are_refused_and_leave_nothing(server: Server) -> None:
    r = _upload(server, b"GIF89a not a tiff", pixel_size="5e-9")
    assert r.status_code == 422 and "TIFF" in r.json()["detail"]
    big = server.services.settings.max_upload_bytes + 1
    r = server.client.post(
        "/api/sem/upload",
        headers={**AUTH, "Content-Length": str(big)},
        content=b"x",
    )
    assert r.status_code == 413
    assert server.client.get("/api/sem").json() == []


def test_instrument_status_and_the_simulated_truth(server: Server) -> None:
    status = server.client.get("/api/instrument").json()
    assert status["simulated"] and status["state"] == "idle" and status["safe_state"]
    assert status["fine_range"] == [1.6e-6, 1.6e-6]
    assert set(status["positions"]) >= {"stage_x", "stage_y"}
    r = server.client.get(
        "/api/instrument/sim/surface",
        params={"x": -1e-6, "y": -2e-6, "width": 2e-6, "height": 1e-6, "pixel": 20e-9},
    )
    assert r.status_code == 200
    truth = np.load(io.BytesIO(r.content))
    assert truth.shape == (51, 101) and truth.std() > 5e-9  # structure, metres
    huge = {"x": 0, "y": 0, "width": 1e-3, "height": 1e-3, "pixel": 1e-9}
    r = server.client.get("/api/instrument/sim/surface", params=huge)
    assert r.status_code == 422 and "larger pixel" in r.json()["detail"]
    far = {"x": 1.0, "y": 0, "width": 1e-6, "height": 1e-6, "pixel": 1e-8}
    r = server.client.get("/api/instrument/sim/surface", params=far)
    assert r.status_code == 422 and "12 mm" in r.json()["detail"]


def test_the_default_sample_has_structure_everywhere_on_20_um(server: Server) -> None:
    """No patch-sized area of the 20 x 20 µm around the origin is featureless."""
    r = server.client.get(
        "/api/instrument/sim/surface",
        params={"x": -10e-6, "y": -10e-6, "width": 20e-6, "height": 20e-6, "pixel": 50e-9},
    )
    truth = np.load(io.BytesIO(r.content))[:400, :400].reshape(20, 20, 20, 20)
    relief = truth.max(axis=(1, 3)) - truth.min(axis=(1, 3))  # per 1 x 1 µm block
    assert relief.min() > 30e-9
