"""What identities cost a request: read and change latency in the single-user mode and in the
users mode (access token, browser cookie, API key), a refused change, and a login.

Starts ``mosaic-afm serve`` on the simulated instrument twice (``MOSAIC_AUTH=single``, then
``users`` with users added by ``mosaic-afm users add``) and times sequential requests from one
client: a run's status (served from memory), the instrument's, and an audited change (take and
release the lock). Prints a table; writes JSON to ``benchmarks/results/access_bench.json`` (or
``--json``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from backend.server_process import AUTH, ServerProcess

ROOT = Path(__file__).resolve().parents[1]
PASSWORD = "benchmark password"
SMALL_RUN = {
    "roi": {"x": -1e-6, "y": -1e-6, "width": 2e-6, "height": 2e-6},
    "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [16, 16]},
    "overlap": [0.25, 0.25],
}


def timed(call: Callable[[], httpx.Response], count: int) -> dict[str, float]:
    """Milliseconds per call: median and 99th percentile (after 10 calls to warm up)."""
    for _ in range(10):
        call()
    times = []
    for _ in range(count):
        t0 = time.perf_counter()
        r = call()
        times.append(time.perf_counter() - t0)
        if r.status_code >= 500:
            raise RuntimeError(f"{r.request.url}: {r.status_code} {r.text[:200]}")
    ms = np.array(times) * 1e3
    return {"p50_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99))}


def lock_cycle(client: httpx.Client, headers: dict[str, str]) -> Callable[[], httpx.Response]:
    def call() -> httpx.Response:
        client.post("/api/lock", json={"note": "bench"}, headers=headers)
        return client.request("DELETE", "/api/lock", headers=headers)

    return call


def single_mode(data: Path, count: int) -> dict[str, dict[str, float]]:
    server = ServerProcess(data, MOSAIC_AUTO_MERGE="false", MOSAIC_VIEWER="false").start()
    try:
        with server.client() as c:
            run = c.post("/api/runs", json=SMALL_RUN, headers=AUTH).json()
            url = f"/api/runs/{run['id']}"
            return {
                "run status, no token": timed(lambda: c.get(url), count),
                "run status, token": timed(lambda: c.get(url, headers=AUTH), count),
                "instrument, token": timed(lambda: c.get("/api/instrument", headers=AUTH), count),
                "take + release the lock, token": timed(lock_cycle(c, AUTH), count // 5),
            }
    finally:
        server.stop()


def add_user(data: Path, name: str, role: str) -> None:
    subprocess.run(
        [sys.executable, "-m", "backend.cli", "users", "--data-dir", str(data), "add", name]
        + ["--role", role],
        input=PASSWORD + "\n",
        text=True,
        check=True,
        capture_output=True,
    )


def users_mode(data: Path, count: int) -> dict[str, dict[str, float]]:
    add_user(data, "olga", "operator")
    add_user(data, "oscar", "operator")
    server = ServerProcess(
        data, MOSAIC_AUTH="users", MOSAIC_AUTO_MERGE="false", MOSAIC_VIEWER="false"
    ).start()
    try:
        with server.client() as c:
            creds = {"username": "olga", "password": PASSWORD}
            logins = timed(lambda: c.post("/api/auth/login", json=creds), 10)
            access = c.post("/api/auth/login", json=creds).json()["access_token"]
            token = {"Authorization": f"Bearer {access}"}
            key = c.post(
                "/api/keys", json={"scopes": ["read", "instrument", "runs"]}, headers=token
            )
            by_key = {"Authorization": f"Bearer {key.json()['key']}"}
            oscar = c.post("/api/auth/login", json={**creds, "username": "oscar"}).json()
            other = {"Authorization": f"Bearer {oscar['access_token']}"}
            run = c.post("/api/runs", json=SMALL_RUN, headers=token).json()
            url = f"/api/runs/{run['id']}"
            with httpx.Client(base_url=server.url, timeout=60) as browser:
                csrf = browser.post("/api/auth/login", json={**creds, "cookie": True}).json()
                cookie_change = {"X-CSRF-Token": csrf["csrf_token"]}
                out = {
                    "run status, access token": timed(lambda: c.get(url, headers=token), count),
                    "run status, API key": timed(lambda: c.get(url, headers=by_key), count),
                    "run status, browser cookie": timed(lambda: browser.get(url), count),
                    "instrument, access token": timed(
                        lambda: c.get("/api/instrument", headers=token), count
                    ),
                    "take + release the lock, access token": timed(
                        lock_cycle(c, token), count // 5
                    ),
                    "take + release the lock, browser cookie": timed(
                        lock_cycle(browser, cookie_change), count // 5
                    ),
                }
            c.post("/api/lock", json={"note": "held"}, headers=token)
            out["a change refused by the lock (423)"] = timed(
                lambda: c.post("/api/runs", json=SMALL_RUN, headers=other), count // 5
            )
            out["login (Argon2)"] = logins
            return out
    finally:
        server.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=500, help="reads per case")
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/access_bench.json"))
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        results: dict[str, Any] = {
            "single": single_mode(Path(tmp) / "single", args.count),
            "users": users_mode(Path(tmp) / "users", args.count),
        }
    print(f"{'mode':<7} {'request':<42} {'p50 ms':>8} {'p99 ms':>8}")
    for mode, cases in results.items():
        for name, t in cases.items():
            print(f"{mode:<7} {name:<42} {t['p50_ms']:8.2f} {t['p99_ms']:8.2f}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
