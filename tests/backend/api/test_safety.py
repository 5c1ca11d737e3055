"""What a hostile or clumsy request can do to the instrument's safety, finding by finding: an
upload that would decode to gigabytes, bodies of any size and encoding, NaN and absurd
numbers, a row that cannot be shown, event streams, hosts and headers, and a crash that must
block the next landing. (The latencies under load are ``benchmarks/server_bench.py``'s.)"""

from __future__ import annotations

import asyncio
import io
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import update

from backend.db.models import Run
from backend.events import QUEUE_SIZE
from tests.backend.api.conftest import AUTH, Server, plan

# the benchmarks are scripts beside each other, not a package
sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "benchmarks"))
from bombs import tiff_declaring


def test_an_sem_tiff_declaring_gigapixels_is_refused_from_its_header(server: Server) -> None:
    for width, height in ((100_000, 100_000), (20_000, 20_000)):
        bomb = tiff_declaring(width, height)
        assert len(bomb) < 1000
        r = server.client.post(
            "/api/sem/upload",
            files={"file": ("bomb.tif", bomb, "image/tiff")},
            data={"pixel_size": "1e-8"},
            headers=AUTH,
        )
        assert r.status_code == 422, r.text
        assert f"declares {height} x {width}" in r.json()["detail"]
    assert server.client.get("/api/sem").json() == []
    assert (
        not list((server.data_dir / "sem").glob("*.npy"))
        if (server.data_dir / "sem").exists()
        else True
    )


def test_a_tiff_scan_declaring_gigapixels_is_refused_in_an_offline_upload(server: Server) -> None:
    bomb = tiff_declaring(100_000, 100_000)
    files = [("files", (f"s{k}.tif", bomb, "image/tiff")) for k in range(2)]
    r = server.client.post(
        "/api/runs/offline", files=files, data={"pixel_size": "1e-8"}, headers=AUTH
    )
    assert r.status_code == 422 and "declares" in r.json()["detail"], r.text


def test_bodies_past_their_limit_are_refused_whatever_their_encoding(server: Server) -> None:
    big = b'{"roi": "' + b"x" * (2 << 20) + b'"}'

    def chunks() -> Iterator[bytes]:  # no Content-Length: Transfer-Encoding chunked
        for k in range(0, len(big), 64 * 1024):
            yield big[k : k + 64 * 1024]

    for content in (big, chunks()):
        r = server.client.post(
            "/api/runs/preview", content=content, headers={"Content-Type": "application/json"}
        )
        assert r.status_code == 413, r.text
        assert "limit" in r.json()["detail"]


def test_a_refused_body_is_never_echoed_nor_a_nan_a_server_error(server: Server) -> None:
    junk = {"roi": {"x": "y" * 200_000, "y": 0, "width": 1e-6, "height": 1e-6}}
    r = server.client.post("/api/runs/preview", json={**plan(), **junk})
    assert r.status_code == 422 and len(r.content) < 4000, len(r.content)
    for literal in ("NaN", "Infinity", "-Infinity"):
        body = (
            '{"roi": {"x": LITERAL, "y": 0, "width": 1e-6, "height": 1e-6}, '
            '"patch": {"width": 8e-7, "height": 8e-7, "pixels": [16, 16]}, '
            '"overlap": [0.25, 0.25]}'
        ).replace("LITERAL", literal)
        r = server.client.post(
            "/api/runs/preview", content=body, headers={"Content-Type": "application/json"}
        )
        assert r.status_code == 422, (literal, r.text)
        assert r.json()["detail"][0]["loc"] == ["body", "roi", "x"]


def test_absurd_numbers_are_refused_with_the_field_to_fix(server: Server) -> None:
    huge = plan()
    huge["roi"]["width"] = 1e308
    r = server.client.post("/api/runs/preview", json=huge)
    assert r.status_code == 422 and r.json()["field"] == "roi.width", r.text
    for rate, words in ((0.01, "outside the scanner"), (60.0, "less than or equal")):
        r = server.client.post("/api/runs/preview", json=plan(line_rate=rate))
        assert r.status_code == 422 and words in r.text, r.text
    fine = plan(pixels=(4096, 4096), patch=1e-6)  # 0.24 nm pixels
    r = server.client.post("/api/runs/preview", json=fine)
    assert r.status_code == 422 and r.json()["field"] in ("patch.pixels", "line_rate"), r.text


def test_an_offline_upload_with_an_absurd_pixel_size_is_refused(server: Server) -> None:
    buffers = []
    for _ in range(2):
        b = io.BytesIO()
        np.save(b, np.zeros((16, 16)))
        buffers.append(b.getvalue())
    files = [("files", (f"s{k}.npy", data, "application/octet-stream"))
             for k, data in enumerate(buffers)]  # fmt: skip
    grid = {"rows": "1", "cols": "2", "overlap_x": "0.25"}
    r = server.client.post(
        "/api/runs/offline", files=files, data={**grid, "pixel_size": "1e307"}, headers=AUTH
    )
    assert r.status_code == 422, r.text
    assert server.client.get("/api/runs").json() == []
    # a name longer than a file system takes is kept short, not a server error
    long = [("files", ("a" * 300 + f"{k}.npy", data, "application/octet-stream"))
            for k, data in enumerate(buffers)]  # fmt: skip
    r = server.client.post(
        "/api/runs/offline", files=long, data={**grid, "pixel_size": "1e-8"}, headers=AUTH
    )
    assert r.status_code == 201, r.text


def test_a_damaged_row_is_listed_with_its_damage_not_a_server_error(server: Server) -> None:
    run = server.create()
    with server.services.sessions() as session:  # as an earlier version could store it
        session.execute(update(Run).where(Run.id == run["id"]).values(roi_width=float("inf")))
        session.commit()
    server.create()
    listed = server.client.get("/api/runs")
    assert listed.status_code == 200, listed.text
    damaged = next(r for r in listed.json() if r["id"] == run["id"])
    assert damaged["roi"]["width"] is None
    assert damaged["damage"] == ["roi_width is inf, not a finite number"]
    assert server.client.get(f"/api/runs/{run['id']}").status_code == 200


def test_event_streams_start_now_and_replay_a_bounded_history(server: Server) -> None:
    for k in range(5):
        server.services.events.emit("note", f"old {k}", data=None)
    latest = server.client.get("/api/events/latest").json()["id"]
    history = server.client.get("/api/events?follow=false").text
    assert history.count("event: note") == 5
    later = server.client.get(f"/api/events?follow=false&after={latest - 2}").text
    assert later.count("event: note") == 2
    assert server.services.events.newest(0, limit=3) == (
        server.services.events.since(latest - 3),
        latest - 3,
    )


def test_hosts_not_ours_are_refused_and_pages_carry_security_headers(server: Server) -> None:
    r = server.client.get("/api/runs", headers={"Host": "attacker.example"})
    assert r.status_code == 400 and "Host" in r.json()["detail"]
    page = server.client.get("/")
    assert page.status_code == 200
    assert "frame-ancestors 'none'" in page.headers["content-security-policy"]
    assert page.headers["x-frame-options"] == "DENY"
    assert page.headers["x-content-type-options"] == "nosniff"


def test_status_is_never_safe_while_a_run_has_the_instrument(server: Server) -> None:
    run = server.create(plan(size=2.5e-6, pixels=(48, 48)))
    server.post(f"/api/runs/{run['id']}/start")
    seen = []
    while True:
        status = server.client.get("/api/instrument").json()
        state = server.client.get(f"/api/runs/{run['id']}").json()["state"]
        if state != "running":
            break
        if status["active_run"] is not None:
            seen.append(status)
    assert seen and all(s["safe_state"] is False for s in seen)
    assert server.client.get("/api/instrument").json()["safe_state"] is True


def slowed_after(server: Server, state: str) -> threading.Event:
    """Set when a run's end in ``state`` is announced; the worker that announced it then
    takes 0.3 s more in its own thread (as on a loaded machine)."""
    heard = threading.Event()

    def slow_listener(event: dict[str, Any]) -> None:
        if event["kind"] == "run" and event["data"].get("state") == state:
            heard.set()
            time.sleep(0.3)

    server.services.events.listen(slow_listener)
    return heard


def test_a_status_read_on_hearing_a_run_completed_finds_the_instrument_safe(
    server: Server,
) -> None:
    """A page reads the instrument when it hears that a run ended; the worker that announced
    it may still be recording (a loaded machine: here a listener that takes 0.3 s). The read
    must not find the instrument still driven by the run: no later event would correct it."""
    heard = slowed_after(server, "completed")
    run = server.create(plan(pixels=(16, 16)))
    server.post(f"/api/runs/{run['id']}/start")
    assert heard.wait(60)
    status = server.client.get("/api/instrument").json()
    assert status["active_run"] is None
    assert status["safe_state"] is True


def test_the_next_run_starts_on_hearing_that_the_last_one_ended(server: Server) -> None:
    """A script starts its next run as soon as it hears the last one was aborted; the worker
    that announced it may still be recording (here a listener taking 0.3 s): the start waits
    for it rather than answering that the instrument is busy."""
    heard = slowed_after(server, "aborted")
    first = server.create(plan(size=4e-6, pixels=(32, 32)))
    second = server.create()
    server.post(f"/api/runs/{first['id']}/start")
    server.wait(first["id"], lambda r: r["progress"]["stored"] >= 1)
    server.post(f"/api/runs/{first['id']}/abort")
    assert heard.wait(60)
    started = server.post(f"/api/runs/{second['id']}/start")
    assert started.status_code == 202, started.text


def test_a_crash_is_a_fault_that_blocks_every_landing_until_a_reset_with_a_note(
    server: Server,
) -> None:
    run = server.create(plan(pixels=(16, 16)))
    rid = run["id"]
    server.post(f"/api/runs/{rid}/start")
    server.wait(rid, lambda r: r["progress"]["stored"] >= 2)
    assert server.post("/api/instrument/sim/fault", {"fault": "crash"}).status_code == 204
    ended = server.wait_state(rid, "fault", "failed", "completed")
    assert ended["state"] == "fault", ended
    assert "crashed" in ended["message"] and "resets the run with a note" in ended["message"]
    status = server.client.get("/api/instrument").json()
    assert status["state"] == "fault" and "crashed" in status["message"]
    assert status["safe_state"] is True  # retracted: safe, but not to be landed
    other = server.create()
    for url in (f"/api/runs/{rid}/resume", f"/api/runs/{other['id']}/start"):
        r = server.post(url)
        assert r.status_code == 409 and "reset" in r.json()["detail"], r.text
    assert server.post(f"/api/runs/{rid}/reset", {"note": ""}).status_code == 422
    # the tip was looked at, not changed: the crashed tip still cannot land
    r = server.post(f"/api/runs/{rid}/reset", {"note": "looked at it"})
    assert r.status_code == 200 and r.json()["state"] == "failed"
    server.post(f"/api/runs/{rid}/resume")
    again = server.wait_state(rid, "fault", "failed", "completed")
    assert again["state"] == "fault" and "PLL lost lock" in again["message"], again
    # a new tip: the run resumes from its first patch not stored and completes
    new_tip = {"note": "tip changed after the crash", "tip_changed": True}
    assert server.post(f"/api/runs/{rid}/reset", new_tip).status_code == 200
    server.post(f"/api/runs/{rid}/resume")
    done = server.wait_state(rid, "completed", "failed", "fault")
    assert done["state"] == "completed", done


def test_a_merge_finer_than_the_scans_can_use_is_refused_before_it_starts(server: Server) -> None:
    run = server.create()  # 50 nm pixels
    for parameters, name in (
        ({"pixel_size": [0.2e-9, 0.2e-9]}, "pixel_size"),
        ({"cell": 1e-9}, "cell"),
    ):
        r = server.post(f"/api/runs/{run['id']}/merges", {"parameters": parameters})
        assert r.status_code == 422 and f"parameters.{name}" in r.json()["detail"], r.text
    assert server.client.get(f"/api/runs/{run['id']}/merges").json() == []


@pytest.mark.slow
def test_an_offline_upload_takes_more_than_a_thousand_files(server: Server) -> None:
    # the multipart parser's default stops at 1,000 files; the route takes its own 2,500
    b = io.BytesIO()
    np.save(b, np.random.default_rng(0).normal(size=(8, 8)) * 1e-9)
    files = [("files", (f"s{k:04d}.npy", b.getvalue(), "application/octet-stream"))
             for k in range(1001)]  # fmt: skip
    grid = {"rows": "7", "cols": "143", "overlap_x": "0.4", "overlap_y": "0.4"}
    r = server.client.post(
        "/api/runs/offline", files=files, data={**grid, "pixel_size": "1e-8"}, headers=AUTH
    )
    assert r.status_code == 201, r.text
    assert r.json()["progress"]["total"] == 1001


def test_a_stream_that_never_reads_is_dropped_with_one_log_line(
    server: Server, caplog: pytest.LogCaptureFixture
) -> None:
    bus = server.services.events
    loop, served = asyncio.new_event_loop(), bus._loop
    try:
        bus.attach(loop)
        queue = bus.subscribe()  # a client that never takes an event
        for k in range(QUEUE_SIZE + 50):
            bus.publish("note", f"n{k}", data=None)
        loop.run_until_complete(asyncio.sleep(0.05))  # the loop hands them over
        assert queue.qsize() == QUEUE_SIZE + 1  # the events it could hold, then its end
        items = [queue.get_nowait() for _ in range(queue.qsize())]
        assert items[-1] is None and queue not in bus._subscribers
    finally:
        if served is not None:
            bus.attach(served)
        loop.close()
    dropped = [r for r in caplog.records if "fell" in r.getMessage()]
    assert len(dropped) == 1
