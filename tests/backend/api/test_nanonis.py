"""The server on a Nanonis controller: the Nanonis and MCS protocol simulators behind it."""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hardware.microscope import SIM_SAMPLE_SIZE
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.surfaces import surface_by_name
from merge.report.evaluate import Grid, score_mosaic
from tests.backend.api.conftest import Server, open_server, plan

#: The paper's grid (5 x 10 patches of 0.6 x 1.2 µm, 50 % / 33 % overlap) at the pixels a
#: Nanonis scan buffer takes (multiples of 16): 18.75 nm.
PAPER_GRID = {
    "roi": {"x": -1.65e-6, "y": -2.2e-6, "width": 3.3e-6, "height": 4.4e-6},
    "patch": {"width": 0.6e-6, "height": 1.2e-6, "pixels": [32, 64]},
    "overlap": [0.5, 1 / 3],
}


@dataclass
class Rig:
    server: Server
    nanonis: NanonisServer

    @property
    def afm(self) -> SimulatedAFM:
        return self.nanonis.afm


@pytest.fixture
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    # the live merge (and with it the quality gate's re-scans) only where a test asks for it
    live = request.node.get_closest_marker("live_merge") is not None
    surface = surface_by_name("folded", seed=0, centred=True, size=SIM_SAMPLE_SIZE)
    with SimulatedAFM(surface, seed=0) as afm, NanonisServer(afm) as nanonis:
        # 2 s: on CI's shared cores a reply can take over half a second (the default is 5 s)
        url = nanonis.instrument_url + "&timeout=2"
        for server in open_server(tmp_path, instrument=url, live_merge=live):
            yield Rig(server, nanonis)


def _tip_is_safe(rig: Rig) -> None:
    afm = rig.afm
    assert not afm.engaged(), "the Z controller is still on"
    assert afm.robot_device.axes[2].extension(afm.clock.now()) == pytest.approx(0.0, abs=1e-9)
    assert not rig.nanonis.controller._busy("scan"), "the scan still runs"
    status = rig.server.client.get("/api/instrument").json()
    assert status["safe_state"] is True and status["loop_engaged"] is False, status


def _score(rig: Rig, job: dict[str, Any], margin: float = 0.3e-6) -> Any:
    client = rig.server.client
    heights = np.load(io.BytesIO(client.get(str(job["mosaic_npy"])).content))
    doc = client.get(str(job["mosaic_json"])).json()
    (ox, oy), (px, py) = doc["origin"], doc["pixel_size"]
    ny, nx = heights.shape
    pitch = 10e-9
    shape = (round((ny * py + 2 * margin) / pitch), round((nx * px + 2 * margin) / pitch))
    truth = rig.afm.true_heights(ox - margin, oy - margin, shape, pitch, tip=True)
    reference = Grid(truth, (ox - margin, oy - margin), (pitch, pitch))
    return score_mosaic(Grid(heights, (ox, oy), (px, py)), reference, tile=(0.6e-6, 0.6e-6))


def _merge(rig: Rig, run_id: int, method: str) -> dict[str, Any]:
    r = rig.server.post(f"/api/runs/{run_id}/merges", {"method": method})
    assert r.status_code == 202, r.text
    job = rig.server.wait_merge(r.json()["id"], timeout=300)
    assert job["state"] == "done", job
    return job


@pytest.mark.slow
def test_a_5_x_10_mosaic_on_the_nanonis_merges_close_to_the_truth(rig: Rig) -> None:
    server = rig.server
    status = server.client.get("/api/instrument").json()
    assert status["description"].startswith("nanonis://") and not status["simulated"]
    run = server.create(PAPER_GRID)
    assert (run["rows"], run["cols"]) == (5, 10)
    server.post(f"/api/runs/{run['id']}/start")
    done = server.wait_state(run["id"], "completed", "failed", "fault", timeout=600)
    assert done["state"] == "completed", done
    job = _merge(rig, run["id"], "default")
    merged = _score(rig, job)
    doc = server.client.get(str(job["mosaic_json"])).json()
    assert doc["parameters"]["self_calibrate"] is True  # chosen for open-loop scans
    bend_x, bend_y = doc["scan_distortion"]["peak_to_valley"]
    assert 3e-9 < bend_y < 30e-9 and bend_x < bend_y, doc["scan_distortion"]
    placed = _score(rig, _merge(rig, run["id"], "nominal"))
    # The sim:// run's bounds (tests/integration/test_server_process.py). The scan piezos run
    # open loop here (hysteresis bow, creep after the move back to a frame's first line, no Y
    # sensor to straighten the rows), so the server's merge takes the scanner's shared bend
    # out (self-calibration); without it: XY 2.2 nm, Z 5.0 nm.
    print(f"merged {merged}\nnominal {placed}")
    assert merged.tile_xy_rms < 2.0e-9
    assert merged.tile_z_rms < 1.5e-9
    assert merged.map_rms < 0.3 * placed.map_rms
    assert merged.tile_xy_rms < 0.2 * placed.tile_xy_rms
    _tip_is_safe(rig)


@pytest.mark.parametrize(
    ("fault", "words"),
    [
        ({"link": "drop", "count": 4}, "link"),
        ({"link": "error", "count": 3, "code": 7}, "error 7"),
        ({"link": "silent", "count": 4}, "no response"),
        ({"link": "short", "count": 4}, "link"),
        ({"link": "garbage", "count": 4}, "garbled"),
        ({"physics": "pll_loss", "after_lines": 5}, "PLL lost lock"),
    ],
    ids=["drop", "error", "silent", "short", "garbage", "pll_loss"],
)
def test_a_nanonis_fault_fails_the_run_in_the_safe_state_then_it_resumes(
    rig: Rig, fault: dict[str, Any], words: str
) -> None:
    server = rig.server
    run = server.create(plan(pixels=(16, 16)))
    rid = run["id"]
    server.post(f"/api/runs/{rid}/start")
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2, timeout=120)
    if "link" in fault:
        rig.nanonis.inject(fault["link"], code=fault.get("code", 1), count=fault["count"])
    else:
        rig.nanonis.inject_physics(fault["physics"], after_lines=fault["after_lines"])
    ended = server.wait_state(rid, "failed", "fault", "completed", timeout=120)
    # a link's fault fails the run; a PLL that loses lock on the surface may have crashed
    # the tip: the run is in fault, and nothing lands until an operator resets it
    crashed = "physics" in fault
    assert ended["state"] == ("fault" if crashed else "failed"), ended
    assert words in ended["message"], ended["message"]
    _tip_is_safe(rig)
    patches = server.client.get(f"/api/runs/{rid}/patches").json()
    assert {p["step"] for p in patches} <= {"pending", "stored"}
    rig.nanonis.inject(None)
    rig.nanonis.inject_physics(None)
    if crashed:
        assert server.post(f"/api/runs/{rid}/resume").status_code == 409
        note = {"note": "tip inspected in the SEM: intact"}
        assert server.post(f"/api/runs/{rid}/reset", note).status_code == 200
    assert server.post(f"/api/runs/{rid}/resume").status_code == 202
    done = server.wait_state(rid, "completed", "failed", timeout=120)
    assert done["state"] == "completed", done
    assert done["progress"]["stored"] == done["progress"]["total"]


@pytest.mark.live_merge
def test_z_at_its_limit_mid_frame_has_the_patch_scanned_again(rig: Rig) -> None:
    """The sample falls away under the tip mid-frame: Z runs into its limit on the lines after.
    The scan's own record fails the patch, the next landing finds the surface lower down, and
    the re-scan is good; the run completes, the re-scan and its reason on record."""
    server = rig.server
    run = server.create(plan(pixels=(16, 16)))
    rid = run["id"]
    server.post(f"/api/runs/{rid}/start")
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2, timeout=120)
    rig.nanonis.inject_physics("z_limit", after_lines=5)
    done = server.wait_state(rid, "completed", "failed", "fault", timeout=120)
    assert done["state"] == "completed", done
    assert any("limit of its range" in r["reason"] for r in done["rescans"]), done["rescans"]
    _tip_is_safe(rig)
