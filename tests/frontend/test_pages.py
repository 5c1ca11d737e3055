"""The operator's pages in a real browser (Debian's chromium, headless, driven by Playwright):
SEM image, ROI drawn with the mouse, plan, run to completion, merge, preview, 3D viewer."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from backend.server_process import AUTH, TOKEN, ServerProcess, free_port
from tests.frontend.conftest import CHROMIUM, _draw_small_roi, _shot, _state, _wait

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="needs Debian's chromium"),
    # one browser and its server at a time: two of them beside the rest on 2 cores made a
    # page's timing-sensitive checks (a live mosaic while the run still scans) fail
    pytest.mark.xdist_group("browser"),
]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    process = ServerProcess(
        tmp_path_factory.mktemp("pages"),
        MOSAIC_AUTO_MERGE="false",
        MOSAIC_VIEWER="true",
        MOSAIC_VIEWER_PORT=str(free_port()),
    ).start()
    yield process
    process.stop()


def test_a_mosaic_from_roi_to_merged_preview(
    page: tuple[Any, list[str]], server: ServerProcess
) -> None:
    pg, errors = page
    pg.click("#sem-acquire")
    pg.wait_for_selector("#sem-canvas[data-sem-id]")
    # the single-user mode: no login, no lock bar (one identity cannot conflict with itself)
    assert not pg.is_visible("#lock-panel") and not pg.is_visible("#logout")
    sem = httpx.get(server.url + "/api/sem").json()[-1]
    # the 512 px image fits the 640 x 480 canvas: scale 480 / 512, centred horizontally
    box = pg.locator("#sem-canvas").bounding_box()
    scale, left = 480 / sem["width"], (640 - sem["width"] * 480 / sem["width"]) / 2
    pitch = sem["pixel_size"][0]
    centre = (sem["width"] / 2 - 0.5, sem["height"] / 2 - 0.5)  # the stage origin, in pixels
    half = (0.9e-6 / pitch, 1.2e-6 / pitch)  # a 1.8 x 2.4 µm region
    x0, y0 = round(left + (centre[0] - half[0]) * scale), round((centre[1] - half[1]) * scale)
    x1, y1 = round(left + (centre[0] + half[0]) * scale), round((centre[1] + half[1]) * scale)
    pg.mouse.move(box["x"] + x0, box["y"] + y0)
    pg.mouse.down()
    for k in range(1, 11):  # a drag, as a hand does it
        pg.mouse.move(box["x"] + x0 + (x1 - x0) * k / 10, box["y"] + y0 + (y1 - y0) * k / 10)
    pg.mouse.up()
    pg.wait_for_selector("#plan-summary[data-count]")
    roi = {
        "sem_id": sem["id"],
        "col": (x0 - left) / scale,
        "row": y0 / scale,
        "width": (x1 - x0) / scale,
        "height": (y1 - y0) / scale,
    }
    expected = httpx.post(
        server.url + "/api/runs/preview",
        json={
            "sem_roi": roi,
            "patch": {"width": 0.6e-6, "height": 1.2e-6, "pixels": [30, 60]},
            "overlap": [0.5, 0.333],
        },
    ).json()
    assert int(pg.get_attribute("#plan-summary", "data-count")) == expected["count"]
    assert expected["count"] >= 12
    _shot(pg, "1-planned")

    pg.click("#create-run")
    pg.wait_for_function("document.querySelector('#run-state').textContent.includes('planned')")
    assert pg.is_enabled("#run-start") and not pg.is_enabled("#run-pause")
    pg.click("#run-start")
    _wait(pg, "document.querySelector('#run-state').textContent.includes('completed')")
    assert pg.locator("#patch-grid img").count() == expected["count"]
    assert pg.inner_text("#run-stored") == f"{expected['count']} / {expected['count']}"
    # the page reads the instrument on hearing the run ended (before the run itself); another
    # event's read of the run may still show "completed" first, so the pill is given a moment
    _wait(pg, "document.querySelector('#safe-state').textContent.includes('SAFE')", 5000)
    _shot(pg, "2-scanned")

    pg.click("#merge-start")
    _wait(pg, "!document.querySelector('#merge-result').hidden")
    pg.wait_for_function(
        "document.querySelector('#merge-preview').complete && "
        "document.querySelector('#merge-preview').naturalWidth > 0"
    )
    assert "done" in pg.inner_text("#merge-state")
    _shot(pg, "3-merged")

    # the mosaic registered on the SEM image it was drawn on, and overlaid
    pg.click("#register-sem")
    _wait(pg, "document.querySelector('#registration').textContent.startsWith('Registered')")
    overlay = "document.querySelector('#sem-overlay')"
    pg.wait_for_function(f"{overlay}.complete && {overlay}.naturalWidth > 0")
    assert "opacity=0.5" in str(pg.get_attribute("#sem-overlay", "src"))
    pg.locator("#overlay-opacity").evaluate(
        "e => { e.value = '0.9'; e.dispatchEvent(new Event('change')); }"
    )
    pg.wait_for_function(f"{overlay}.src.includes('opacity=0.9') && {overlay}.complete")
    # a profile line dragged across the overlay: heights and SEM signal along it
    pg.locator("#overlay-box").scroll_into_view_if_needed()
    box = pg.locator("#profile-line").bounding_box()
    assert box is not None
    with pg.expect_response(lambda r: "/sem-profile" in r.url) as answer:
        pg.mouse.move(box["x"] + 0.2 * box["width"], box["y"] + 0.5 * box["height"])
        pg.mouse.down()
        pg.mouse.move(box["x"] + 0.8 * box["width"], box["y"] + 0.45 * box["height"], steps=5)
        pg.mouse.up()
    cut = answer.value.json()
    assert sum(h is not None for h in cut["height"]) > 100  # the line lies over the mosaic
    assert all(v is not None for v in cut["sem"])
    pg.wait_for_function("!document.querySelector('#profile-plot').hidden")
    inked = pg.locator("#profile-plot").evaluate(
        "c => { const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }"
    )
    assert inked > 500  # two traces and their labels drawn
    _shot(pg, "5-overlay")
    pg.reload()  # a reload shows the run's last merge, its registration and overlay again
    _wait(pg, "document.querySelector('#registration').textContent.startsWith('Registered')")
    pg.wait_for_function(f"{overlay}.complete && {overlay}.naturalWidth > 0")
    for _ in range(100):  # and the 3D viewer drapes the SEM over the merged mosaic
        if httpx.get(server.url + "/api/instrument/viewer").json()["nodes"]["draped"]:
            break
        pg.wait_for_timeout(100)
    assert httpx.get(server.url + "/api/instrument/viewer").json()["nodes"]["draped"]

    # the 3D viewer holds one node per stored patch and the merged mosaic
    viewer: dict[str, Any] = {}
    for _ in range(100):
        viewer = httpx.get(server.url + "/api/instrument/viewer").json()
        if viewer["nodes"]["merged"] and len(viewer["nodes"]["raw"]) == expected["count"]:
            break
        pg.wait_for_timeout(100)
    assert len(viewer["nodes"]["raw"]) == expected["count"]
    assert len(viewer["nodes"]["merged"]) == 1
    assert errors == [], errors


def _plan_an_impossible_overlap(pg: Any) -> None:
    """Draw an ROI on an SEM image (acquired if none is shown) and ask for a 95 % overlap."""
    if not pg.get_attribute("#sem-canvas", "data-sem-id"):
        pg.click("#sem-acquire")
        pg.wait_for_selector("#sem-canvas[data-sem-id]")
    _draw_small_roi(pg)
    pg.fill("input[name=ox]", "95")
    pg.wait_for_function("document.querySelector('#plan-error').textContent.includes('overlap')")


def test_an_image_acquired_while_the_page_starts_is_kept_with_its_roi(
    page: tuple[Any, list[str]],
) -> None:
    # the page shows the latest stored image once it has started; an operator who acquires one
    # and draws an ROI before that must not lose both to the older image
    pg, errors = page
    held: list[Any] = []
    pg.route("**/api/sem", lambda route: held.append(route))  # the list of stored images
    pg.reload()
    for _ in range(100):
        if held:
            break
        pg.wait_for_timeout(100)
    assert held, "the page did not ask for the stored images"
    pg.click("#sem-acquire")
    pg.wait_for_selector("#sem-canvas[data-sem-id]")
    acquired = pg.get_attribute("#sem-canvas", "data-sem-id")
    _draw_small_roi(pg)
    assert pg.input_value("input[name=roi_width]") != ""
    with pg.expect_response("**/api/sem"):
        for route in held:
            route.continue_()
    pg.unroute("**/api/sem")
    pg.wait_for_timeout(500)  # the page's start finishes
    assert pg.get_attribute("#sem-canvas", "data-sem-id") == acquired
    assert pg.input_value("input[name=roi_width]") != ""
    assert errors == [], errors


def test_no_older_image_is_shown_while_the_sem_acquires_the_one_asked_for(
    page: tuple[Any, list[str]], server: ServerProcess
) -> None:
    # the operator asks for an image while the page starts: the latest stored one, arriving
    # meanwhile, must not be shown (an ROI drawn on it would be dropped when the new one comes)
    pg, errors = page
    body = {"centre": [0, 0], "field": 5e-6, "pixels": 64}
    assert httpx.post(server.url + "/api/sem/acquire", json=body, headers=AUTH).status_code < 300
    held: list[Any] = []
    pg.route("**/api/sem/acquire", lambda route: held.append(route))
    with pg.expect_response("**/api/sem"):  # the page's start reads the stored images
        pg.reload()
        pg.click("#sem-acquire")
    pg.wait_for_timeout(1000)  # time for the latest stored image to be fetched and drawn
    assert pg.get_attribute("#sem-canvas", "data-sem-id") is None
    assert held, "the page did not ask the SEM for an image"
    with pg.expect_response("**/api/sem/acquire") as answer:
        held[0].continue_()
    acquired = answer.value.json()["id"]
    pg.unroute("**/api/sem/acquire")
    pg.wait_for_selector(f"#sem-canvas[data-sem-id='{acquired}']")
    assert errors == [], errors


def test_a_refused_request_shows_the_servers_message(page: tuple[Any, list[str]]) -> None:
    pg, errors = page
    pg.fill("#token", "not-the-token-at-all")
    pg.press("#token", "Tab")
    pg.click("#sem-acquire")
    pg.wait_for_selector("#message:not([hidden])")
    assert "Bearer" in pg.inner_text("#message") and "401" in pg.inner_text("#message")
    _shot(pg, "4-refused")
    # an impossible overlap is refused inline, naming the field
    pg.fill("#token", TOKEN)
    pg.press("#token", "Tab")
    _plan_an_impossible_overlap(pg)
    assert pg.get_attribute("input[name=ox]", "aria-invalid") == "true"
    assert pg.is_disabled("#create-run")
    # errors the page showed on purpose are not console errors of the page itself
    assert [e for e in errors if "401" not in e and "422" not in e] == []


def test_a_late_answer_to_an_older_plan_does_not_undo_a_refusal(
    page: tuple[Any, list[str]],
) -> None:
    pg, _ = page
    held: list[Any] = []

    def hold_valid(route: Any) -> None:
        # hold back the answers for the still-valid form; let the refused one through at once
        if route.request.post_data_json.get("overlap", [0])[0] < 0.9:
            held.append(route)
        else:
            route.continue_()

    pg.route("**/api/runs/preview", hold_valid)
    _plan_an_impossible_overlap(pg)
    assert held, "the older previews were not held back"
    with pg.expect_response("**/api/runs/preview"):
        for route in held:
            route.continue_()
    pg.unroute("**/api/runs/preview")  # what the page asks from now on goes straight through
    pg.wait_for_timeout(300)  # let the late answers reach the page's handlers
    # a refusal on show always goes with a disabled "create run"
    refused = "overlap" in pg.inner_text("#plan-error")
    assert not refused or pg.is_disabled("#create-run"), _state(pg)


def test_a_plan_made_with_the_keyboard_alone(page: tuple[Any, list[str]]) -> None:
    pg, errors = page
    pg.focus("input[name=roi_x]")
    for value in ("-1.65", "-2.2", "3.3", "4.4"):  # x, y, width, height; Tab between them
        pg.keyboard.type(value)
        pg.keyboard.press("Tab")
    pg.wait_for_function(
        "document.querySelector('#plan-summary').textContent.includes('50 patches')"
    )
    for _ in range(20):  # on through the patch fields to the button
        if pg.evaluate("document.activeElement.id") == "create-run":
            break
        pg.keyboard.press("Tab")
    assert pg.evaluate("document.activeElement.id") == "create-run"
    assert errors == [], errors


def test_the_pages_run_under_their_content_security_policy_and_open_the_viewer(
    browser: Any, server: ServerProcess
) -> None:
    context = browser.new_context(viewport={"width": 1280, "height": 800})  # CSP enforced
    pg = context.new_page()
    errors: list[str] = []
    pg.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    answer = pg.goto(server.url + "/")
    headers = answer.headers
    assert "frame-ancestors 'none'" in headers["content-security-policy"]
    assert headers["x-frame-options"] == "DENY"
    pg.fill("#token", TOKEN)
    pg.press("#token", "Tab")
    pg.wait_for_selector("#viewer[src]", state="attached")
    pg.locator("#viewer").scroll_into_view_if_needed()  # an offscreen frame does not draw
    api = httpx.Client(base_url=server.url, timeout=30)
    for _ in range(200):  # the page's viewer, let in with the token's cookie
        if api.get("/api/instrument/viewer").json()["browsers"] >= 1:
            break
        pg.wait_for_timeout(50)
    assert api.get("/api/instrument/viewer").json()["browsers"] >= 1
    context.close()
    assert errors == [], errors


def test_a_token_typed_while_the_page_still_loads_opens_the_viewer(
    browser: Any, server: ServerProcess
) -> None:
    """The page's first answer held until the token is typed: the token is kept and opens the
    viewer (on loaded cores the page used to drop it and ask for it again)."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    pg = context.new_page()
    held: list[Any] = []
    pg.route("**/api/auth/whoami", lambda route: held.append(route))
    pg.goto(server.url + "/")
    pg.fill("#token", TOKEN)
    pg.press("#token", "Tab")
    for _ in range(200):  # the page asked who it is before the token was typed
        if held:
            break
        pg.wait_for_timeout(50)
    assert held, "the page did not ask who it is"
    held[0].continue_()
    pg.unroute("**/api/auth/whoami")
    pg.wait_for_selector("#viewer[src]", state="attached", timeout=15_000)
    assert pg.input_value("#token") == TOKEN
    context.close()


def test_the_api_token_header_works_for_scripts_too(server: ServerProcess) -> None:
    r = httpx.post(server.url + "/api/runs/999/start", headers=AUTH)
    assert r.status_code == 404


def test_the_live_mosaic_grows_in_the_viewer_and_a_rescanned_patch_shows_on_the_page(
    page: tuple[Any, list[str]], server: ServerProcess
) -> None:
    pg, errors = page
    api = httpx.Client(base_url=server.url, headers=AUTH, timeout=30)
    spoil = {"fault": "z_jump", "patches": [4], "count": 1}
    assert api.post("/api/instrument/sim/fault", json=spoil).status_code == 204
    body = {
        "roi": {"x": -1e-6, "y": -1e-6, "width": 2e-6, "height": 2e-6},
        "patch": {"width": 0.8e-6, "height": 0.8e-6, "pixels": [32, 32]},
        "overlap": [0.3, 0.3],
    }
    run = api.post("/api/runs", json=body).json()
    rid = run["id"]
    pg.reload()  # the page lists the runs there are, the newest shown
    pg.wait_for_selector(f"#run-select option[value='{rid}']", state="attached")
    if pg.input_value("#run-select") != str(rid):
        pg.select_option("#run-select", str(rid))
    pg.wait_for_function("document.querySelector('#run-state').textContent.includes('planned')")
    assert api.post(f"/api/runs/{rid}/start").status_code == 202
    # the viewer shows the live mosaic while the run still scans
    live_while_scanning = False
    for _ in range(1200):
        nodes = api.get("/api/instrument/viewer").json()["nodes"]
        state = api.get(f"/api/runs/{rid}").json()["state"]
        if nodes["live"] and state == "running":
            live_while_scanning = nodes["live"] == [f"/merged/live{rid}"]
            break
        if state not in ("planned", "running"):
            break
        pg.wait_for_timeout(50)
    assert live_while_scanning
    # the spoiled patch is re-scanned, and the page shows it as such
    _wait(pg, "document.querySelector('#patch-grid [data-quality=\"rescanned\"]') !== null")
    _wait(pg, "document.querySelector('#run-state').textContent.includes('completed')")
    rescanned = pg.locator('#patch-grid [data-quality="rescanned"]')
    assert "re-scanned" in (rescanned.first.get_attribute("title") or "")
    indices = {int(i) for i in rescanned.evaluate_all("els => els.map(e => e.dataset.index)")}
    assert 4 in indices
    assert pg.locator('#patch-grid [data-quality="ok"]').count() >= 16 - len(indices)
    _shot(pg, "4-rescanned")
    assert errors == [], errors
