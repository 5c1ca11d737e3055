"""The browser the page tests drive (Debian's chromium, headless, through Playwright), a page
on the module's ``server`` with the token entered, and what the tests do on it."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from backend.server_process import TOKEN, ServerProcess

playwright_api = pytest.importorskip("playwright.sync_api")

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
SHOTS = Path(__file__).resolve().parents[1] / "screenshots"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        b = p.chromium.launch(
            executable_path=CHROMIUM,
            headless=True,
            args=[
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
            ],
        )
        yield b
        b.close()


@pytest.fixture
def page(browser: Any, server: ServerProcess) -> Iterator[tuple[Any, list[str]]]:
    # Playwright's wait_for_function evaluates its predicate with eval, which the pages'
    # Content-Security-Policy forbids: these tests lift it (one test below keeps it)
    context = browser.new_context(viewport={"width": 1280, "height": 800}, bypass_csp=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(server.url + "/")
    pg.fill("#token", TOKEN)
    pg.press("#token", "Tab")  # change event: the token is kept
    yield pg, errors
    context.close()


def _state(pg: Any) -> str:
    """What the page says, for a failure message."""
    ids = ["message", "plan-error", "run-state", "run-message", "merge-state", "merge-error"]
    return "; ".join(f"#{i}: {pg.inner_text('#' + i)!r}" for i in ids)


#: How long the page may take to show what the server finishes (a run of 48 patches, a merge):
#: long, since a busy CI machine ran such a run 6 x slower than an idle one (a 120 s wait
#: failed there); a page that never gets there still fails, later.
FINISH_MS = 600_000


def _wait(pg: Any, condition: str, timeout: float = FINISH_MS) -> None:
    try:
        pg.wait_for_function(condition, timeout=timeout)
    except playwright_api.TimeoutError:
        _shot(pg, "failure")
        raise AssertionError(f"never true: {condition} ({_state(pg)})") from None


def _shot(pg: Any, name: str) -> None:
    SHOTS.mkdir(exist_ok=True)
    pg.screenshot(path=str(SHOTS / f"{name}.png"), full_page=True)


def _draw_small_roi(pg: Any) -> None:
    """Drag a small ROI on the SEM image shown."""
    box = pg.locator("#sem-canvas").bounding_box()
    pg.mouse.move(box["x"] + 300, box["y"] + 200)
    pg.mouse.down()
    pg.mouse.move(box["x"] + 360, box["y"] + 260)
    pg.mouse.up()
