"""Offline runs: overlapping scans from any AFM uploaded, merged and exported through the API."""

from __future__ import annotations

import io
from pathlib import Path

import httpx
import numpy as np
import pytest

from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from hardware.sim.synth import synthesize
from merge.io.formats.gwy import write_gwy
from tests.backend.api.conftest import AUTH, Server


def _scans(tmp_path: Path, suffix: str) -> list[Path]:
    synth = synthesize(
        FoldedSurface(seed=4),
        rows=2,
        cols=2,
        patch_size=(0.8e-6, 0.8e-6),
        pixels=(40, 40),
        overlap=(0.4, 0.4),
        drift=DriftModel.typical(),
        seed=3,
    )
    paths = []
    for s in synth:
        path = tmp_path / f"{s.id}{suffix}"
        if suffix == ".gwy":
            write_gwy(path, s.heights, pixel_size=s.pixel_size, origin=s.origin)
        else:
            np.save(path, s.heights)
        paths.append(path)
    return paths


def _upload(server: Server, paths: list[Path], **form: str) -> httpx.Response:
    files = [("files", (p.name, p.read_bytes(), "application/octet-stream")) for p in paths]
    return server.client.post("/api/runs/offline", headers=AUTH, files=files, data=form)


def test_gwy_scans_with_offsets_merge_and_export(server: Server, tmp_path: Path) -> None:
    r = _upload(server, _scans(tmp_path, ".gwy"))
    assert r.status_code == 201, r.text
    run = r.json()
    assert run["state"] == "completed" and run["progress"] == {"stored": 4, "total": 4}
    assert run["instrument"] == "offline upload"
    job = server.post(f"/api/runs/{run['id']}/merges", {}).json()
    done = server.wait_merge(job["id"])
    assert done["state"] == "done", done
    gwy = server.client.get(f"/api/merges/{job['id']}/mosaic.gwy")
    assert gwy.status_code == 200 and gwy.content.startswith(b"GWYP")
    for fmt in ("tif", "png", "ply", "stl"):
        assert server.client.get(f"/api/merges/{job['id']}/mosaic.{fmt}").status_code == 200
    assert server.client.get(f"/api/merges/{job['id']}/mosaic.xyz").status_code == 404


def test_npy_scans_need_a_grid_and_a_pixel_size(server: Server, tmp_path: Path) -> None:
    paths = _scans(tmp_path, ".npy")
    r = _upload(server, paths)
    assert r.status_code == 422 and "pixel size" in r.json()["detail"]
    r = _upload(server, paths, pixel_size="2e-8")
    assert r.status_code == 422 and "rows, cols" in r.json()["detail"]
    r = _upload(
        server, paths, pixel_size="2e-8", rows="2", cols="2", overlap_x="0.4", overlap_y="0.4"
    )
    assert r.status_code == 201, r.text
    patches = r.json()["patches"]
    assert [(p["row"], p["col"]) for p in patches] == [(0, 0), (0, 1), (1, 1), (1, 0)]
    heights = np.load(
        io.BytesIO(server.client.get(f"/api/runs/{r.json()['id']}/patches/2/data").content)
    )
    np.testing.assert_array_equal(heights, np.load(paths[2]))


def test_unreadable_uploads_are_refused(server: Server, tmp_path: Path) -> None:
    bad = tmp_path / "bad.nid"
    bad.write_text("not a nid")
    other = tmp_path / "x.doc"
    other.write_text("?")
    r = _upload(server, [bad, bad])
    assert r.status_code == 422 and "Nanosurf" in r.json()["detail"]
    r = _upload(server, [other, other])
    assert r.status_code == 422 and "unknown format" in r.json()["detail"]
    assert server.client.get("/api/runs").json() == []


def test_numbered_nanoscope_captures_place_by_offset(server: Server, tmp_path: Path) -> None:
    from tests.merge.io.formats.test_nanoscope import write_nanoscope

    rng = np.random.default_rng(2)
    raw = rng.integers(-3000, 3000, (24, 32))
    paths = []
    for k, x in enumerate(("0 nm", "1000 nm")):
        paths.append(tmp_path / f"sample.{k + 1:03d}")
        height = ("Height", raw, 2, 439.9, "Sens. Zsens", "Retrace")
        write_nanoscope(paths[-1], [height], scan_size="2 2 ~m", offset=(x, "0 nm"))
    r = _upload(server, paths)
    assert r.status_code == 201, r.text
    origins = [p["origin"] for p in r.json()["patches"]]
    assert origins[1][0] - origins[0][0] == pytest.approx(1e-6)
    write_nanoscope(paths[1], [height], scan_size="2 2 ~m", offset=("0 nm", "0 nm"))
    r = _upload(server, paths)
    assert r.status_code == 422 and "share one scan offset" in r.json()["detail"]


def _uploads_left(server: Server) -> list[Path]:
    folder = server.data_dir / "uploads"
    return sorted(folder.iterdir()) if folder.exists() else []


def test_refused_uploads_leave_nothing_and_name_no_server_path(
    server: Server, tmp_path: Path
) -> None:
    paths = _scans(tmp_path, ".npy")
    for form in ({}, {"pixel_size": "2e-8"}):  # no pixel size; then no grid
        r = _upload(server, paths, **form)
        assert r.status_code == 422, r.text
        assert str(server.data_dir) not in r.json()["detail"], r.json()["detail"]
    bad = tmp_path / "bad.nid"
    bad.write_text("not a nid")
    assert _upload(server, [bad, bad]).status_code == 422
    assert _uploads_left(server) == []
    ok = _upload(server, paths, pixel_size="2e-8", rows="2", cols="2")
    assert ok.status_code == 201 and len(_uploads_left(server)) == 1


def test_an_npy_whose_header_claims_more_than_its_bytes_is_refused(
    server: Server, tmp_path: Path
) -> None:
    liar = tmp_path / "liar.npy"
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (60000, 60000), }"
    raw = b"\x93NUMPY\x01\x00" + len(header.ljust(118) + "\n").to_bytes(2, "little")
    liar.write_bytes(raw + (header.ljust(118) + "\n").encode() + bytes(80))
    r = _upload(server, [liar, liar], pixel_size="2e-8", rows="1", cols="2")
    assert r.status_code == 422, r.text
    assert "60000" in r.json()["detail"] and "liar.npy" in r.json()["detail"]
    big = tmp_path / "big.npy"
    np.save(big, np.zeros((4097, 4096), dtype=np.float32))
    r = _upload(server, [big, big], pixel_size="2e-8", rows="1", cols="2")
    assert r.status_code == 422 and "more than" in r.json()["detail"], r.text
    assert _uploads_left(server) == []
