"""Plan, run, merge and download a mosaic through the REST API, as a script would.

Start a server first (``make run``), then::

    MOSAIC_API_TOKEN=... python examples/scripted_run.py --url http://127.0.0.1:8000 --out out/run

The token is the server's (``MOSAIC_API_TOKEN``, or the file ``api_token`` in its data dir);
on a server in the users mode (``MOSAIC_AUTH=users``) it is an API key with the scopes
``read``, ``runs`` and ``merges`` (``POST /api/keys``), which also reads.
Writes ``mosaic.npy`` and ``mosaic.json`` into ``--out`` and prints a one-line summary.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import httpx

#: The paper's grid: 5 x 10 patches of 0.6 x 1.2 µm, 50 % / 33 % overlap, 20 nm pixels.
PLAN = {
    "roi": {"x": -1.65e-6, "y": -2.2e-6, "width": 3.3e-6, "height": 4.4e-6},
    "patch": {"width": 0.6e-6, "height": 1.2e-6, "pixels": [30, 60]},
    "overlap": [0.5, 1 / 3],
}
#: ``--quick``: 3 x 3 patches of 0.8 µm, a minute's mosaic on a busy machine
QUICK = {
    "roi": {"x": -1e-6, "y": -1e-6, "width": 2e-6, "height": 2e-6},
    "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [32, 32]},
    "overlap": [0.25, 0.25],
}


def wait(client: httpx.Client, url: str, done: Any, timeout: float) -> dict[str, Any]:
    """Poll ``url`` until ``done(body)``; print progress on one line."""
    deadline = time.monotonic() + timeout
    while True:
        body: dict[str, Any] = client.get(url).json()
        progress = body.get("progress")
        print(f"\r{url}: {body['state']} {progress}   ", end="", file=sys.stderr, flush=True)
        if done(body):
            print(file=sys.stderr)
            return body
        if time.monotonic() > deadline:
            raise TimeoutError(f"{url} still {body['state']} after {timeout} s")
        time.sleep(0.5)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000")
    parser.add_argument("--out", default="out/scripted-run")
    parser.add_argument("--token", default=os.environ.get("MOSAIC_API_TOKEN"))
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per stage")
    parser.add_argument(
        "--quick", action="store_true", help="3 x 3 patches, not the paper's 5 x 10"
    )
    args = parser.parse_args(argv)
    if not args.token:
        parser.error("give --token or set MOSAIC_API_TOKEN (the server's api_token file)")
    auth = {"Authorization": f"Bearer {args.token}", "X-Operator": "scripted_run.py"}
    with httpx.Client(base_url=args.url, timeout=60, headers=auth) as client:
        r = client.post("/api/runs", json=QUICK if args.quick else PLAN)
        if r.status_code != 201:
            print(f"planning refused ({r.status_code}): {r.json()['detail']}", file=sys.stderr)
            return 2
        run = r.json()
        print(f"run {run['id']}: {run['rows']} x {run['cols']} patches", file=sys.stderr)
        client.post(f"/api/runs/{run['id']}/start").raise_for_status()
        run = wait(
            client,
            f"/api/runs/{run['id']}",
            lambda b: b["state"] not in ("planned", "running", "paused"),
            args.timeout,
        )
        if run["state"] != "completed":
            print(f"run ended {run['state']}: {run['message']}", file=sys.stderr)
            return 1
        job = client.post(f"/api/runs/{run['id']}/merges", json={"method": "default"}).json()
        job = wait(
            client,
            f"/api/merges/{job['id']}",
            lambda b: b["state"] in ("done", "failed", "cancelled"),
            args.timeout,
        )
        if job["state"] != "done":
            print(f"merge {job['state']}: {job['message']}", file=sys.stderr)
            return 1
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "mosaic.npy").write_bytes(client.get(job["mosaic_npy"]).content)
        document = client.get(job["mosaic_json"]).json()
        (out / "mosaic.json").write_text(json.dumps(document, indent=1), encoding="utf-8")
    print(
        f"run {run['id']} merged: {document['shape'][1]} x {document['shape'][0]} px, "
        f"{document['iterations']} iterations -> {out}/mosaic.npy"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
