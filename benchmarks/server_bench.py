"""The acquisition server from outside: a 50-patch mosaic end to end, and status-read latency
while a run and a merge are in progress.

Starts ``mosaic-afm serve`` on the simulated instrument at maximum simulated speed in a
temporary data dir. Targets (issue 4): plan to merged mosaic for the paper's 5 x 10 grid in
under 60 s on 2 cores; p99 of status reads under 50 ms during a run and a merge. Prints a
table; writes JSON to ``benchmarks/results/server_bench.json`` (or ``--json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from backend.server_process import AUTH, ServerProcess, wait_for

ROOT = Path(__file__).resolve().parents[1]
PAPER_GRID = {
    "roi": {"x": -1.65e-6, "y": -2.2e-6, "width": 3.3e-6, "height": 4.4e-6},
    "patch": {"width": 0.6e-6, "height": 1.2e-6, "pixels": [30, 60]},
    "overlap": [0.5, 1 / 3],
}
BIG_RUN = {
    "roi": {"x": -4e-6, "y": -4e-6, "width": 8e-6, "height": 8e-6},
    "patch": {"width": 1e-6, "height": 1e-6, "pixels": [64, 64]},
    "overlap": [0.2, 0.2],
}


def end_to_end(client: httpx.Client) -> dict[str, Any]:
    """Plan, scan, merge and download the paper's grid; seconds for each stage."""
    t0 = time.perf_counter()
    run = client.post("/api/runs", json=PAPER_GRID, headers=AUTH).json()
    client.post(f"/api/runs/{run['id']}/start", headers=AUTH).raise_for_status()
    wait_for(client, f"/api/runs/{run['id']}", lambda b: b["state"] == "completed", poll=0.02)
    t_scan = time.perf_counter()
    job = client.post(f"/api/runs/{run['id']}/merges", json={}, headers=AUTH).json()
    job = wait_for(client, f"/api/merges/{job['id']}", lambda b: b["state"] == "done", poll=0.02)
    client.get(job["mosaic_npy"]).raise_for_status()
    t_end = time.perf_counter()
    return {
        "run_id": run["id"],
        "patches": run["progress"]["total"],
        "scan_s": t_scan - t0,
        "merge_s": t_end - t_scan,
        "total_s": t_end - t0,
    }


def _reader(base: str, urls: list[str], deadline: float, out: dict[str, list[float]]) -> None:
    """One client reading ``urls`` in turn until ``deadline``; seconds per read into ``out``."""
    with httpx.Client(base_url=base, timeout=10) as reader:
        while time.monotonic() < deadline:
            for url in urls:
                t = time.perf_counter()
                reader.get(url).raise_for_status()
                out[url].append(time.perf_counter() - t)
            time.sleep(0.01)


def latency_under_load(
    client: httpx.Client, run_id: int, seconds: float, *, clients: int = 1
) -> dict[str, Any]:
    """Status reads by ``clients`` clients at once while a big run scans and merges of
    ``run_id`` run back to back."""
    big = client.post("/api/runs", json=BIG_RUN, headers=AUTH).json()
    client.post(f"/api/runs/{big['id']}/start", headers=AUTH).raise_for_status()
    stop = threading.Event()
    merges = {"count": 0}

    def merging() -> None:
        while not stop.is_set():
            job = client.post(f"/api/runs/{run_id}/merges", json={}, headers=AUTH).json()
            wait_for(client, f"/api/merges/{job['id']}", lambda b: b["state"] == "done")
            merges["count"] += 1

    worker = threading.Thread(target=merging, daemon=True)
    worker.start()
    time.sleep(1.0)  # the merge process is up and busy
    urls = [f"/api/runs/{big['id']}", "/api/instrument"]
    if clients == 1:
        urls += ["/api/runs", "/api/merges/1"]
    per_client: list[dict[str, list[float]]] = [{u: [] for u in urls} for _ in range(clients)]
    deadline = time.monotonic() + seconds
    readers = [
        threading.Thread(target=_reader, args=(str(client.base_url), urls, deadline, out))
        for out in per_client
    ]
    for reader in readers:
        reader.start()
    for reader in readers:
        reader.join()
    states = {client.get(f"/api/runs/{big['id']}").json()["state"]}
    samples = {u: [t for out in per_client for t in out[u]] for u in urls}
    stop.set()
    client.post(f"/api/runs/{big['id']}/abort", json={"reason": "benchmark over"}, headers=AUTH)
    # the abort may answer while the tip is still retracted: the next case's run waits for it
    wait_for(client, f"/api/runs/{big['id']}", lambda b: b["state"] not in ("running", "paused"))
    worker.join(60)
    every = np.concatenate([np.asarray(v) for v in samples.values()])
    return {
        "clients": clients,
        "reads": int(every.size),
        "p50_ms": float(np.percentile(every, 50) * 1e3),
        "p99_ms": float(np.percentile(every, 99) * 1e3),
        "max_ms": float(every.max() * 1e3),
        "per_route_p99_ms": {
            u.replace(f"/{big['id']}", "/{id}"): float(np.percentile(v, 99) * 1e3)
            for u, v in samples.items()
        },
        "merges_completed": merges["count"],
        "run_states_seen": sorted(states),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--json", default=str(ROOT / "benchmarks" / "results" / "server_bench.json")
    )
    parser.add_argument("--seconds", type=float, default=15.0, help="latency sampling time")
    parser.add_argument("--clients", type=int, default=20, help="concurrent status readers")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        server = ServerProcess(Path(tmp), MOSAIC_AUTO_MERGE="false").start()
        try:
            with httpx.Client(base_url=server.url, timeout=60) as client:
                e2e = end_to_end(client)
                print(
                    f"end to end, {e2e['patches']} patches: scan {e2e['scan_s']:.1f} s + merge "
                    f"{e2e['merge_s']:.1f} s = {e2e['total_s']:.1f} s (target < 60 s)",
                    flush=True,
                )
                lat = [
                    latency_under_load(client, e2e["run_id"], args.seconds, clients=n)
                    for n in (1, args.clients)
                ]
        finally:
            server.stop()
    print(f"{'route':<28}" + "".join(f"{f'p99 ms, {x}':>14}" for x in ("1 client", "20")))
    for url in lat[1]["per_route_p99_ms"]:
        print(f"{url:<28}" + "".join(f"{r['per_route_p99_ms'][url]:>14.1f}" for r in lat))
    for r in lat:
        print(
            f"status reads by {r['clients']} client(s) during a run and a merge: {r['reads']} "
            f"reads, p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms (target: 1 client < 50 "
            f"ms, 20 < 100 ms), max {r['max_ms']:.1f} ms; {r['merges_completed']} merges"
        )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(
        json.dumps({"end_to_end": e2e, "latency": lat[0], "latency_20": lat[1]}, indent=1) + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
