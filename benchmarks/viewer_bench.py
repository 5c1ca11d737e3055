"""The 3D viewer: time from a finished merge to its mosaic sent to a browser showing the viewer.

For the paper's 50-patch grid and a 20 x 20 grid of 64 x 64 patches: merge a synthetic set,
store the result in a run file as the server does, then time what the server does when the
merge-done event arrives (read the result, decimate, build the coloured mesh, send it to the
connected browser: Debian's chromium, headless, with the viewer open). Targets (issue 5):
under 2 s and under 5 s. Writes JSON to ``benchmarks/results/viewer_bench.json``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from backend.db.patch_store import read_merge, write_merge
from backend.server_process import free_port
from backend.synthetic import patch_set_from_synth
from backend.viewer import HeightMap, Viewer
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import FoldedSurface
from hardware.sim.synth import synthesize
from merge import run as merge_run
from merge.io.result import result_document

ROOT = Path(__file__).resolve().parents[1]
CASES = [
    ("50 patches (30 x 60)", 5, 10, (0.6e-6, 1.2e-6), (30, 60), (0.5, 1 / 3), 2.0),
    ("400 patches (64 x 64)", 20, 20, (1.0e-6, 1.0e-6), (64, 64), (0.2, 0.2), 5.0),
]


def _browser(url: str) -> Any:
    """A headless chromium page on the viewer, so the scene really goes somewhere."""
    from playwright.sync_api import sync_playwright

    p = sync_playwright().start()
    browser = p.chromium.launch(
        executable_path=shutil.which("chromium") or "/usr/bin/chromium",
        args=["--no-sandbox", "--disable-gpu", "--disable-background-networking"],
    )
    page = browser.new_page()
    page.goto(url)
    page.wait_for_timeout(2000)  # connected
    return p, browser


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--json", default=str(ROOT / "benchmarks" / "results" / "viewer_bench.json")
    )
    args = parser.parse_args(argv)
    viewer = Viewer(port=free_port())
    p, browser = _browser(viewer.url)
    rows = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for name, r, c, size, pixels, overlap, target in CASES:
                synth = synthesize(
                    FoldedSurface(seed=3),
                    rows=r,
                    cols=c,
                    patch_size=size,
                    pixels=pixels,
                    overlap=overlap,
                    drift=DriftModel.typical(),
                    seed=1,
                )
                result = merge_run(patch_set_from_synth(synth))
                path = Path(tmp) / f"{r}x{c}.h5"
                group = write_merge(path, 1, result.mosaic.heights, result_document(result))
                start = time.perf_counter()  # the merge-done event arrives here
                heights, doc = read_merge(path, group)
                viewer.show_mosaic(
                    r * c,
                    HeightMap(heights, tuple(doc["origin"]), tuple(doc["pixel_size"])),
                )
                seconds = time.perf_counter() - start
                ny, nx = heights.shape
                rows.append(
                    {
                        "case": name,
                        "mosaic_px": [nx, ny],
                        "seconds": seconds,
                        "target_s": target,
                    }
                )
                print(
                    f"{name:<24} mosaic {nx} x {ny} px: shown in {seconds:.2f} s "
                    f"(target < {target:g} s)",
                    flush=True,
                )
    finally:
        browser.close()
        p.stop()
        viewer.close()
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"viewer": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
