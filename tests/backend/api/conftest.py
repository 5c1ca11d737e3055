"""A server on the simulated instrument, in-process (the real app, database, HDF5, serial)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from backend.api.app import create_app
from backend.services import Services
from backend.settings import Settings

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}", "X-Operator": "tester"}


def plan(
    *,
    size: float = 2.0e-6,
    patch: float = 0.8e-6,
    pixels: tuple[int, int] = (16, 16),
    overlap: tuple[float, float] = (0.25, 0.25),
    **extra: Any,
) -> dict[str, Any]:
    """A small mosaic around the origin: 3 x 3 patches by default."""
    return {
        "roi": {"x": -size / 2, "y": -size / 2, "width": size, "height": size},
        "patch": {"width": patch, "height": patch, "pixels": list(pixels)},
        "overlap": list(overlap),
        **extra,
    }


@dataclass
class Server:
    client: TestClient
    services: Services
    data_dir: Path

    def post(self, url: str, json: Any = None, **kw: Any) -> Any:
        return self.client.post(url, json=json, headers=AUTH, **kw)

    def create(self, body: dict[str, Any] | None = None) -> dict[str, Any]:
        r = self.post("/api/runs", body or plan())
        assert r.status_code == 201, r.text
        run: dict[str, Any] = r.json()
        return run

    def wait(
        self, run_id: int, until: Callable[[dict[str, Any]], bool], timeout: float = 90.0
    ) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            run: dict[str, Any] = self.client.get(f"/api/runs/{run_id}").json()
            if until(run):
                return run
            if time.monotonic() > deadline:
                raise AssertionError(f"run {run_id} never got there: {run}")
            time.sleep(0.02)

    def wait_state(self, run_id: int, *states: str, timeout: float = 90.0) -> dict[str, Any]:
        return self.wait(run_id, lambda r: r["state"] in states, timeout)

    def wait_merge(self, job_id: int, timeout: float = 120.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            job: dict[str, Any] = self.client.get(f"/api/merges/{job_id}").json()
            if job["state"] in ("done", "failed", "cancelled"):
                return job
            if time.monotonic() > deadline:
                raise AssertionError(f"merge {job_id} never ended: {job}")
            time.sleep(0.05)


def open_server(tmp_path: Path, **settings: Any) -> Iterator[Server]:
    cfg = Settings(
        data_dir=tmp_path,
        api_token=TOKEN,
        auto_merge=settings.pop("auto_merge", False),
        # the live merge is a second process merging every stored patch: a core's worth of load
        # the tests of it ask for (live_merge=True), and the others do without
        live_merge=settings.pop("live_merge", False),
        viewer=settings.pop("viewer", False),
        instrument=settings.pop("instrument", "sim://?speed=max"),
        hosts=settings.pop("hosts", ["testserver"]),
        **settings,
    )
    services = Services.open(cfg)
    try:
        with TestClient(create_app(cfg, services=services)) as client:
            yield Server(client, services, tmp_path)
    finally:
        services.close()


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    yield from open_server(tmp_path)
