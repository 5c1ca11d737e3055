"""A whole run on an AFM-in-SEM whose every part speaks its own wire protocol: the Nanonis
controller and its MCS sample stage, and a TESCAN SEM over SharkSEM, all through HTTP."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from hardware.microscope import SIM_SAMPLE_SIZE
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.sem import SimulatedSEM
from hardware.sim.sharksem_server import SharkSEMServer
from hardware.sim.surfaces import surface_by_name
from tests.backend.api.conftest import Server, open_server

FIELD = 20e-6


@dataclass
class Rig:
    server: Server
    sem: SharkSEMServer


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    surface = surface_by_name("folded", seed=0, centred=True, size=SIM_SAMPLE_SIZE)
    with SimulatedAFM(surface, seed=0) as afm, NanonisServer(afm) as nanonis:
        seen = SimulatedSEM(
            surface, seed=0, stage=afm.stage_position, sensor_scale=afm.stage_sensor_scale
        )
        with SharkSEMServer(seen).start() as sem:
            url = f"{nanonis.instrument_url}&timeout=2&sem={sem.url}"
            for server in open_server(tmp_path, instrument=url):
                yield Rig(server, sem)


@pytest.mark.slow
def test_calibrate_draw_on_the_sem_and_run_behind_three_wire_protocols(rig: Rig) -> None:
    server = rig.server
    status = server.client.get("/api/instrument").json()
    assert "sem=sharksem://" in status["description"] and not status["simulated"]
    r = server.post("/api/sem/calibrate", {"field": FIELD, "pixels": 256})
    assert r.status_code == 201, r.text
    found = r.json()
    truth = rig.sem.sem.true_map()
    assert found["rotation_deg"] == pytest.approx(truth["rotation_deg"], abs=0.05)
    for scale in found["scale"]:
        assert scale / (FIELD / 256) == pytest.approx(truth["scale"], rel=1e-3)
    image = server.post("/api/sem/acquire", {"field": FIELD, "pixels": 256})
    assert image.status_code == 201, image.text
    sem = image.json()
    assert sem["calibration_id"] == found["id"] and sem["source"] == "acquired (SE)"
    # an ROI of 24 x 24 px around the field's centre: 2 x 2 patches of 1.2 µm
    drawn = {"sem_id": sem["id"], "col": 116.0, "row": 116.0, "width": 24.0, "height": 24.0}
    body = {
        "sem_roi": drawn,
        "patch": {"width": 1.2e-6, "height": 1.2e-6, "pixels": [32, 32]},
        "overlap": [0.3, 0.3],
    }
    run = server.create(body)
    assert run["sem"]["sem_id"] == sem["id"] and run["sem"]["calibration_id"] == found["id"]
    assert run["sem"]["rotation_deg"] == pytest.approx(found["rotation_deg"])
    assert server.post(f"/api/runs/{run['id']}/start").status_code == 202
    done = server.wait_state(run["id"], "completed", "failed", "fault", timeout=600)
    assert done["state"] == "completed", done
    r = server.post(f"/api/runs/{run['id']}/merges", {"method": "default"})
    assert r.status_code == 202, r.text
    assert server.wait_merge(r.json()["id"], timeout=300)["state"] == "done"
    served = list(rig.sem.log)
    for command in ("TcpRegDataPort", "SetViewField", "DtSelect", "DtEnable", "ScScanXY"):
        assert command in served, command
    assert served.count("ScScanXY") == 1 + 2 * 24 + 1  # the calibration's frames, the image


def test_an_sem_fault_is_a_clear_502_and_the_next_frame_comes_on_a_new_link(rig: Rig) -> None:
    server = rig.server
    rig.sem.inject("drop_data", count=100)
    r = server.post("/api/sem/acquire", {"field": FIELD, "pixels": 128})
    assert r.status_code == 502, r.text
    assert "nothing was stored" in r.json()["detail"]
    assert server.client.get("/api/sem").json() == []
    rig.sem.inject(None)
    r = server.post("/api/sem/acquire", {"field": FIELD, "pixels": 128})
    assert r.status_code == 201, r.text
    assert np.asarray(r.json()["matrix"]).shape == (2, 2)


def test_the_sem_reports_its_field_rotation_and_stage(rig: Rig) -> None:
    server = rig.server
    rig.sem.stage = (1e-3, -2e-3, 0.012)
    assert server.post("/api/sem/acquire", {"field": 12e-6, "pixels": 64}).status_code == 201
    state = server.client.get("/api/sem/microscope").json()
    assert state["field"] == pytest.approx(12e-6)
    assert state["stage"] == pytest.approx([1e-3, -2e-3, 0.012])
    assert state["scan_rotation_deg"] == 0.0
