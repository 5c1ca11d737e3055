"""
A scripted run on the simulated instrument
==========================================

What a script does over the REST API (:doc:`/rest-api`): plan a mosaic, start it, follow it
until it completes, merge it and download the heights. The server here is ``mosaic-afm
serve`` on the simulated instrument at full simulated speed, in a data directory of its own;
the same calls drive a real instrument.
"""

import io
import tempfile
import time
from pathlib import Path

import httpx
import matplotlib.pyplot as plt
import numpy as np

from backend.server_process import AUTH, ServerProcess

# %%
# Start a server (the single-user mode: its token in ``AUTH``).
data = Path(tempfile.mkdtemp(prefix="mosaic-gallery-"))
server = ServerProcess(data, MOSAIC_AUTO_MERGE="false", MOSAIC_VIEWER="false").start()
api = httpx.Client(base_url=server.url, headers=AUTH, timeout=60)


def follow(url, done, timeout=300.0):
    """Poll ``url`` until ``done(body)``."""
    deadline = time.monotonic() + timeout
    while not done(body := api.get(url).json()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{url}: {body}")
        time.sleep(0.2)
    return body


# %%
# Plan 3 x 3 patches of 0.8 µm (32 x 32 px, 25 % overlaps) around the stage origin; start.
plan = {
    "roi": {"x": -1e-6, "y": -1e-6, "width": 2e-6, "height": 2e-6},
    "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [32, 32]},
    "overlap": [0.25, 0.25],
}
run = api.post("/api/runs", json=plan).json()
print(f"run {run['id']}: {run['rows']} x {run['cols']} patches, {run['state']}")
api.post(f"/api/runs/{run['id']}/start").raise_for_status()
run = follow(f"/api/runs/{run['id']}", lambda r: r["state"] not in ("planned", "running"))
print(f"run {run['id']}: {run['state']}, {run['progress']['stored']} patches stored")

# %%
# Merge it and fetch the mosaic (heights in metres, NaN where no patch lies).
job = api.post(f"/api/runs/{run['id']}/merges", json={"method": "default"}).json()
job = follow(f"/api/merges/{job['id']}", lambda j: j["state"] in ("done", "failed"))
print(f"merge {job['id']}: {job['state']} after {job['iteration']} iterations")
heights = np.load(io.BytesIO(api.get(job["mosaic_npy"]).content))
document = api.get(job["mosaic_json"]).json()

# %%
# The merged mosaic.
fig, ax = plt.subplots(figsize=(5, 4.2), constrained_layout=True)
shown = ax.imshow(heights * 1e9, origin="lower", cmap="afmhot")
ax.set(title=f"run {run['id']}, merged", xlabel="x (px)", ylabel="y (px)")
fig.colorbar(shown, ax=ax, label="height (nm)")
plt.show()

api.close()
server.stop()
