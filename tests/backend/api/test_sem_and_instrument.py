"""SEM images (acquired, uploaded TIFFs), ROIs drawn on them, the instrument's state and truth."""

from __future__ import annotations

import io
from pathlib import Path

import httpx
import numpy as np
import pytest
import tifffile

from hardware.microscope import ConfigurationError, open_microscope
from tests.backend.api.conftest import AUTH, Server, open_server


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


def _vendor_tiff(vendor: str) -> bytes:
    """A 64 x 48 px SEM TIFF of ``vendor`` saying: 12.5 nm pixels, scanned turned 5°, the SEM
    stage at (1.25, -2.5, 10) mm."""
    pixels = (np.arange(64 * 48).reshape(48, 64) % 251).astype(np.uint8)
    if vendor == "fei":  # [Beam] ScanRotation in radians, [Stage] in metres
        text = (
            "[User]\nDate=12/06/2026\n[Beam]\nScanRotation=0.0872664626\n"
            "[Scan]\nPixelWidth=1.25e-08\nPixelHeight=1.25e-08\n"
            "[Stage]\nStageX=0.00125\nStageY=-0.0025\nStageZ=0.01\n"
        )
        tag = (34682, "s", 0, text, True)
    elif vendor == "zeiss":  # SmartSEM's CZ_SEM tag, tifffile's parse of it
        text = "\r\n".join(
            ["0", "AP_IMAGE_PIXEL_SIZE", "Image Pixel Size = 12.5 nm",
             "AP_SCANROTATION", "Scan Rotation = 5.0 deg",
             "AP_STAGE_AT_X", "Stage at X = 1.25 mm", "AP_STAGE_AT_Y", "Stage at Y = -2.5 mm",
             "AP_STAGE_AT_Z", "Stage at Z = 10.0 mm", "END"]
        )  # fmt: skip
        tag = (34118, "s", 0, text, True)
    else:  # TESCAN's header
        text = (
            "[MAIN]\nPixelSizeX=1.25e-08\nPixelSizeY=1.25e-08\nScanRotation=5.0\n"
            "StageX=0.00125\nStageY=-0.0025\nStageZ=0.01\n"
        )
        tag = (50431, "s", 0, text, True)
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, pixels, extratags=[tag])
    return buffer.getvalue()


@pytest.mark.parametrize("vendor", ["fei", "zeiss", "tescan"])
def test_an_upload_is_placed_as_its_vendors_tags_say(server: Server, vendor: str) -> None:
    r = _upload(server, _vendor_tiff(vendor), origin_x="1e-6", origin_y="2e-6")
    assert r.status_code == 201, r.text
    sem = r.json()
    assert sem["pixel_size"] == pytest.approx([12.5e-9, 12.5e-9])
    assert sem["rotation_deg"] == pytest.approx(5.0)
    assert sem["sem_stage"] == pytest.approx([1.25e-3, -2.5e-3, 10e-3])
    a = np.deg2rad(5.0)
    # rows go down the screen: a step along a row is +x turned by 5°, down a column -y turned
    expected = [[12.5e-9 * np.cos(a), 12.5e-9 * np.sin(a)],
                [12.5e-9 * np.sin(a), -12.5e-9 * np.cos(a)]]  # fmt: skip
    np.testing.assert_allclose(sem["matrix"], expected, rtol=1e-9)
    # an ROI drawn on it covers the turned rectangle: 40 x 20 px from the origin
    body = {
        "sem_roi": {"sem_id": sem["id"], "col": 0, "row": 0, "width": 40, "height": 20},
        "patch": {"width": 0.6e-6, "height": 0.6e-6, "pixels": [16, 16]},
        "overlap": [0.25, 0.25],
    }
    plan = server.client.post("/api/runs/preview", json=body).json()
    assert plan["roi"]["width"] == pytest.approx(500e-9 * np.cos(a) + 250e-9 * np.sin(a))
    assert plan["roi"]["y"] == pytest.approx(2e-6 - 250e-9 * np.cos(a))  # the rows go down


def test_an_upload_without_tags_takes_the_rotation_it_is_given(server: Server) -> None:
    data = _tiff(np.zeros((32, 32), dtype=np.uint16))
    r = _upload(server, data, pixel_size="5e-9", rotation="-30")
    assert r.status_code == 201, r.text
    assert r.json()["rotation_deg"] == -30.0
    a = np.deg2rad(-30.0)
    np.testing.assert_allclose(
        r.json()["matrix"],
        [[5e-9 * np.cos(a), 5e-9 * np.sin(a)], [5e-9 * np.sin(a), -5e-9 * np.cos(a)]],
    )


def test_the_simulated_sem_is_rotated_and_scaled_against_the_stage(tmp_path: Path) -> None:
    for server in open_server(
        tmp_path, instrument="sim://?speed=max&sem_rotation=-4&sem_scale=0.98"
    ):
        truth = server.client.get("/api/instrument/sim/sem").json()
        assert truth["rotation_deg"] == -4.0 and truth["scale"] == 0.98
        assert len(truth["offset"]) == 2
        r = server.post("/api/sem/acquire", {"field": 8e-6, "pixels": 64, "dwell": 2e-6})
        assert r.status_code == 201, r.text
        assert server.client.get("/api/instrument/sim/sem").json()["offset"] != truth["offset"]
        state = server.client.get("/api/sem/microscope").json()
        assert state["field"] == 8e-6 and len(state["stage"]) == 3
    with pytest.raises(ConfigurationError, match="sem_scale"):
        open_microscope("sim://?sem_scale=5")
