"""The users mode in a real browser: log in, see who holds the instrument, take it when it is
free, run a mosaic, and find your name in the audit trail."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from backend.server_process import ServerProcess, free_port
from tests.frontend.conftest import CHROMIUM, FINISH_MS, _shot, playwright_api
from tests.frontend.test_pages import pytestmark  # noqa: F401  (chromium, slow, one at a time)

PASSWORD = "a password of the lab"


def add(data_dir: Path, name: str, role: str) -> None:
    """``mosaic-afm users add`` as an admin types it, the password on standard input."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "backend.cli",
            "users",
            "--data-dir",
            str(data_dir),
            "add",
            name,
            "--role",
            role,
        ],
        input=PASSWORD + "\n",
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    data = tmp_path_factory.mktemp("users-page")
    add(data, "alice", "admin")
    add(data, "bob", "operator")
    process = ServerProcess(
        data,
        MOSAIC_AUTH="users",
        MOSAIC_AUTO_MERGE="false",
        MOSAIC_VIEWER="false",
        MOSAIC_VIEWER_PORT=str(free_port()),
    ).start()
    yield process
    process.stop()


def api_login(server: ServerProcess, name: str) -> dict[str, str]:
    r = httpx.post(server.url + "/api/auth/login", json={"username": name, "password": PASSWORD})
    assert r.status_code == 200, r.text
    return {"Authorization": f"Bearer {r.json()['access_token']}"}


def test_log_in_take_the_instrument_run_and_find_it_in_the_audit(server: ServerProcess) -> None:
    bob = api_login(server, "bob")
    held = httpx.post(
        server.url + "/api/lock", json={"note": "calibrating, back at 10"}, headers=bob
    )
    assert held.status_code == 200
    with playwright_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=["--no-sandbox"])
        # a token this browser kept from a single-mode server at the same address: the
        # page must not send it in place of the login's cookie
        left = {"name": "mosaic-afm-token", "value": "left-over-single-mode-token"}
        context = browser.new_context(
            viewport={"width": 1280, "height": 800},
            storage_state={
                "cookies": [],
                "origins": [{"origin": server.url, "localStorage": [left]}],
            },
        )
        pg = context.new_page()
        errors: list[str] = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        try:
            _journey(pg, server, bob)
        except Exception:
            _shot(pg, "users-failure")
            raise
        finally:
            context.close()
            browser.close()
    assert not errors


def _journey(pg: Any, server: ServerProcess, bob: dict[str, str]) -> None:
    pg.goto(server.url + "/")
    pg.wait_for_url("**/login.html")  # nobody logged in: the login page
    pg.fill("#username", "alice")
    pg.fill("#password", "not it")
    pg.click("#login-button")
    pg.wait_for_selector("#login-error:has-text('wrong user name or password')")
    pg.fill("#password", PASSWORD)
    # the page's start held after it shows the lock and before it listens to events
    held: list[Any] = []
    gate = {"open": False}

    def hold(route: Any) -> None:
        if gate["open"]:
            route.continue_()
        else:
            held.append(route)

    pg.route("**/api/instrument", hold)
    pg.click("#login-button")
    pg.wait_for_selector("#who:has-text('alice · admin')")
    # bob holds the instrument: his name and note are shown, taking it is not offered
    pg.wait_for_selector("#lock-state:has-text('Held by bob')")
    assert "calibrating, back at 10" in pg.inner_text("#lock-state")
    assert not pg.is_enabled("#lock-take")
    assert pg.inner_text("#lock-release") == "Break the lock"  # an admin's
    _shot(pg, "users-1-held")
    # bob releases it while the page still starts; the page hears it on the event stream
    assert httpx.request("DELETE", server.url + "/api/lock", headers=bob).status_code == 200
    for _ in range(200):
        if held:
            break
        pg.wait_for_timeout(50)
    assert held, "the page did not read the instrument"
    gate["open"] = True
    for route in held:
        route.continue_()
    pg.wait_for_selector("#lock-state:has-text('Instrument free')")
    pg.fill("#lock-note", "mosaic of sample 12")
    pg.click("#lock-take")
    pg.wait_for_selector("#lock-state:has-text('You hold the instrument')")
    # bob, no longer the holder, is refused a run, by alice's name
    refused = httpx.post(
        server.url + "/api/runs",
        json={
            "roi": {"x": -1e-6, "y": -1e-6, "width": 2e-6, "height": 2e-6},
            "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [16, 16]},
            "overlap": [0.25, 0.25],
        },
        headers=bob,
    )
    assert refused.status_code == 423
    assert "alice holds the instrument" in refused.json()["detail"]
    # alice plans and runs a small mosaic from the typed ROI
    for name, value in {
        "roi_x": "-1",
        "roi_y": "-1",
        "roi_width": "2",
        "roi_height": "2",
        "patch_width": "0.8",
        "patch_height": "0.8",
        "nx": "16",
        "ny": "16",
        "ox": "25",
        "oy": "25",
    }.items():
        pg.fill(f"input[name={name}]", value)
    pg.wait_for_selector("#plan-summary[data-count]")
    pg.click("#create-run")
    pg.wait_for_selector("#run-state:has-text('planned')")
    pg.click("#run-start")
    pg.wait_for_selector("#run-state:has-text('completed')", timeout=FINISH_MS)
    _shot(pg, "users-2-ran")
    # the audit trail, read by alice: her lock, her run, bob's refusal
    pg.click("#audit-link")
    pg.wait_for_selector("#audit-rows tr")
    text = pg.inner_text("#audit-rows")
    for action in ("take_lock", "create_run", "start_run"):
        assert any("alice" in line and action in line for line in text.splitlines()), (
            f"no row of alice's {action}:\n{text}"
        )
    assert any("bob" in line and "refused (423)" in line for line in text.splitlines())
    pg.fill("#f-user", "bob")
    pg.click("#filters button")
    who = pg.locator("#audit-rows tr td:nth-child(2)")
    for _ in range(100):  # the filtered rows replace the others (no eval: the page's CSP)
        names = who.all_inner_texts()
        if names and set(names) == {"bob"}:
            break
        pg.wait_for_timeout(50)
    assert set(who.all_inner_texts()) == {"bob"}
    _shot(pg, "users-3-audit")
