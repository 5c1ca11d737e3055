"""Take the documentation's pictures of the mosaic on the SEM image from a real server and a
real browser: a mosaic scanned and merged on the simulated instrument, registered onto the
SEM image taken before it; the page's overlay with a profile line (``docs/overlay.png``) and
the 3D viewer with the raw patches in height colours beside the merged mosaic with the SEM
draped over it (``docs/viewer-draped.png``).

Run: ``.venv/bin/python docs/screenshots.py`` (a few minutes; needs chromium). The viewer
draws with WebGL, which headless chromium does in software (SwiftShader).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from backend.server_process import AUTH, TOKEN, ServerProcess  # noqa: E402

#: The mosaic: 4 x 4 patches of 1.2 µm over 4 µm, on a 20 µm SEM view.
ROI, PATCH, FIELD = 4e-6, 1.2e-6, 20e-6


def _until(what: str, check: Any, timeout: float = 600.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = check()
        if value:
            return value
        time.sleep(0.5)
    raise SystemExit(f"timed out waiting for {what}")


def _merged_and_registered(url: str) -> int:
    """A mosaic scanned, merged and registered on an SEM image; the merge's id."""
    with httpx.Client(base_url=url, headers=AUTH, timeout=120) as api:
        sem = api.post("/api/sem/acquire", json={"field": FIELD, "pixels": 1024}).json()
        body = {
            "roi": {"x": -ROI / 2, "y": -ROI / 2, "width": ROI, "height": ROI},
            "patch": {"width": PATCH, "height": PATCH, "pixels": [96, 96]},
            "overlap": [0.25, 0.25],
        }
        run = api.post("/api/runs", json=body).json()
        api.post(f"/api/runs/{run['id']}/start").raise_for_status()
        _until("the run", lambda: api.get(f"/api/runs/{run['id']}").json()["state"] == "completed")
        job = api.post(f"/api/runs/{run['id']}/merges", json={"method": "default"}).json()
        _until("the merge", lambda: api.get(f"/api/merges/{job['id']}").json()["state"] == "done")
        found = api.post(f"/api/merges/{job['id']}/sem-registration", json={"sem": sem["id"]})
        if not found.json()["accepted"]:
            raise SystemExit(f"the registration was refused: {found.json()['reason']}")
        return int(job["id"])


def _shoot(url: str, out: Path) -> None:
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=chromium,
            headless=True,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        pg = browser.new_page(viewport={"width": 1280, "height": 900})
        pg.goto(url + "/")
        pg.fill("#token", TOKEN)
        pg.press("#token", "Tab")
        pg.wait_for_selector("#sem-overlay", state="visible", timeout=60_000)
        pg.wait_for_function(
            "() => { const o = document.querySelector('#sem-overlay');"
            " return o.complete && o.naturalWidth > 0; }"
        )
        pg.locator("#overlay-box").scroll_into_view_if_needed()
        box = pg.locator("#profile-line").bounding_box()
        assert box is not None
        pg.mouse.move(box["x"] + 0.15 * box["width"], box["y"] + 0.55 * box["height"])
        pg.mouse.down()
        pg.mouse.move(box["x"] + 0.85 * box["width"], box["y"] + 0.45 * box["height"], steps=8)
        pg.mouse.up()
        pg.wait_for_selector("#profile-plot", state="visible")
        pg.wait_for_timeout(500)
        pg.locator("#overlay-box").screenshot(path=str(out / "overlay.png"))
        # the viewer on its own port, the SEM chosen as the merged mosaic's colour
        viewer = pg.frame_locator("#viewer")
        viewer.get_by_text("Colour").first.wait_for(timeout=60_000)
        frame = pg.locator("#viewer")
        frame.scroll_into_view_if_needed()
        viewer.get_by_role("combobox", name="Colour").click()
        viewer.get_by_role("option", name="SEM").click()
        notice = viewer.get_by_text("Software WebGL rendering detected")
        if notice.count():  # viser's notice that the browser draws without a GPU
            notice.locator("xpath=../..").get_by_role("button").first.click()
        pg.wait_for_timeout(8000)  # the draped node, drawn in software
        frame.screenshot(path=str(out / "viewer-draped.png"))
        browser.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "docs", help="where the pictures go")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        server = ServerProcess(Path(tmp), MOSAIC_AUTO_MERGE="false").start()
        try:
            _merged_and_registered(server.url)
            _shoot(server.url, args.out)
        finally:
            server.stop()
    print(f"wrote {args.out / 'overlay.png'} and {args.out / 'viewer-draped.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
