"""The Nanonis path against sim://: patches per wall second, and command round trips.

Scans the same snake-ordered mosaic on the same simulated world twice at maximum simulated
speed: once on ``sim://`` (the software rasters the robot's fine axes over MCS links), once on
``nanonis://...?stage=mcs:...`` (the Nanonis simulator's scan generator, its TCP protocol and
the MCS stage), through the same procedures the server runs (move, prepare, land, scan,
retract). Prints patches per wall second, the ratio per patch (target: Nanonis at most 1.5 x
sim://), and the round trip of a Nanonis command on loopback (p50, p99). Then the 50 patches
of both paths merged (as the server does, and with self-calibration switched the other way)
and scored against the world's truth: map error, tile XY and Z (the sim:// run's bounds: XY
< 2 nm, Z < 1.5 nm). Writes JSON to ``benchmarks/results/nanonis_bench.json`` (or
``--json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from hardware.microscope import Microscope, open_microscope, simulated_afm
from hardware.mosaic_plan import snake_grid
from hardware.nanonis.client import NanonisClient
from hardware.procedures import move_stage, retract, sample_origin
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.surfaces import Chessboard
from merge import MergeConfig, Patch, PatchSet, run
from merge.report.evaluate import Grid, score_mosaic

ROOT = Path(__file__).resolve().parents[1]
#: the world both paths scan (the Nanonis simulator builds the same one)
SIM = "sim://?surface=chessboard&seed=1&speed=max"
#: name, rows, cols, pixels (multiples of 16 for the scan buffer), patch size, line rate (Hz)
CASES = [
    ("50 x (32 x 64)", 5, 10, (32, 64), (0.6e-6, 1.2e-6), 2.0),
    ("4 x (256 x 256)", 2, 2, (256, 256), (1.2e-6, 1.2e-6), 0.5),
]


def scan_all(
    m: Microscope,
    rows: int,
    cols: int,
    pixels: tuple[int, int],
    size: tuple[float, float],
    line_rate: float,
) -> list[Patch]:
    """Every patch of the grid, as the runner does it, at its sample-frame origin."""
    _, loop, scanner = m.require_afm()
    plan = snake_grid(rows, cols, patch_size=size, overlap=(0.5, 1 / 3))
    out = []
    for k, planned in enumerate(plan):
        move_stage(m.stage_x, m.stage_y, m.robot_x, m.robot_y, origin=planned.origin, size=size)
        scanner.prepare(size=size, pixels=pixels)
        m.land()
        lines = scanner.scan(size=size, pixels=pixels, line_rate=line_rate)
        retract(m.robot_z, loop)
        origin = sample_origin(
            lines, m.stage_x, m.stage_y, planned=planned.origin, size=size, x=m.robot_x, y=m.robot_y
        )
        out.append(Patch(f"p{k:03d}", lines.heights, origin, lines.pixel_size, order=k))
    return out


def accuracy(
    patches: list[Patch], world: SimulatedAFM, *, self_calibrate: bool
) -> dict[str, float]:
    """The merged mosaic's errors against the truth of ``world``, nanometres."""
    result = run(PatchSet(patches), MergeConfig(self_calibrate=self_calibrate))
    mosaic, margin, pitch = result.mosaic, 0.3e-6, 10e-9
    (ox, oy), (px, py) = mosaic.origin, mosaic.pixel_size
    ny, nx = mosaic.heights.shape
    shape = (round((ny * py + 2 * margin) / pitch), round((nx * px + 2 * margin) / pitch))
    truth = world.true_heights(ox - margin, oy - margin, shape, pitch, tip=True)
    score = score_mosaic(
        Grid(mosaic.heights, (ox, oy), (px, py)),
        Grid(truth, (ox - margin, oy - margin), (pitch, pitch)),
        tile=(0.6e-6, 0.6e-6),
    )
    bend = result.distortion.peak_to_valley if result.distortion else (0.0, 0.0)
    return {
        "map_nm": score.map_rms * 1e9,
        "tile_xy_nm": score.tile_xy_rms * 1e9,
        "tile_z_nm": score.tile_z_rms * 1e9,
        "bend_x_nm": bend[0] * 1e9,
        "bend_y_nm": bend[1] * 1e9,
    }


def round_trips(server: NanonisServer, n: int = 2000) -> dict[str, float]:
    """Seconds per ``ZCtrl.ZPosGet`` request and response on loopback."""
    with NanonisClient.open(*server.address) as client:
        times = np.empty(n)
        for i in range(n):
            start = time.perf_counter()
            client.z_position()
            times[i] = time.perf_counter() - start
    return {
        "p50_ms": float(np.percentile(times, 50)) * 1e3,
        "p99_ms": float(np.percentile(times, 99)) * 1e3,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--json", default=str(ROOT / "benchmarks" / "results" / "nanonis_bench.json")
    )
    parser.add_argument("--quick", action="store_true", help="the first case only")
    args = parser.parse_args(argv)
    rows: list[dict[str, Any]] = []
    scanned: dict[str, list[Patch]] = {}
    print(f"{'case':<18}{'path':<10}{'patches':>8}{'wall s':>9}{'patches/s':>11}{'x sim':>7}")
    for name, r, c, pixels, size, line_rate in CASES[:1] if args.quick else CASES:
        walls = {}
        for path in ("sim", "nanonis"):
            if path == "sim":
                m = open_microscope(SIM)
                server = None
            else:
                server = NanonisServer(simulated_afm(SIM)).start()
                m = open_microscope(server.instrument_url)
            try:
                start = time.perf_counter()
                patches = scan_all(m, r, c, pixels, size, line_rate)
                walls[path] = time.perf_counter() - start
                n = len(patches)
                if not scanned.get(path):
                    scanned[path] = patches  # the first case's, for the accuracy table
            finally:
                m.close()
                if server is not None:
                    server.stop()
                    server.afm.close()
            ratio = walls[path] / walls["sim"]
            rows.append(
                {
                    "case": name,
                    "path": path,
                    "patches": n,
                    "wall_s": walls[path],
                    "patches_per_s": n / walls[path],
                    "per_patch_vs_sim": ratio,
                }
            )
            print(
                f"{name:<18}{path:<10}{n:>8}{walls[path]:>9.2f}{n / walls[path]:>11.2f}"
                f"{ratio:>7.2f}",
                flush=True,
            )
    with SimulatedAFM(Chessboard(seed=1), seed=1) as afm, NanonisServer(afm) as server:
        rtt = round_trips(server)
    print(
        f"Nanonis command round trip on loopback: p50 {rtt['p50_ms']:.3f} ms, "
        f"p99 {rtt['p99_ms']:.3f} ms"
    )
    print(f"\nmerged {CASES[0][0]} against the truth (nm; sim:// bounds XY < 2, Z < 1.5)")
    print(
        f"{'path':<10}{'self-calibrate':>15}{'map':>7}{'XY':>7}{'Z':>7}{'bend x':>8}{'bend y':>8}"
    )
    scores = []
    with simulated_afm(SIM) as world:  # the world both paths scanned, for its truth
        for path, patches in scanned.items():
            server_choice = path == "nanonis"  # the server self-calibrates open-loop scans only
            for calibrate in (server_choice, not server_choice):
                a = accuracy(patches, world, self_calibrate=calibrate)
                scores.append({"path": path, "self_calibrate": calibrate, **a})
                print(
                    f"{path:<10}{str(calibrate) + (' *' if calibrate == server_choice else ''):>15}"
                    f"{a['map_nm']:>7.2f}{a['tile_xy_nm']:>7.2f}{a['tile_z_nm']:>7.2f}"
                    f"{a['bend_x_nm']:>8.2f}{a['bend_y_nm']:>8.2f}",
                    flush=True,
                )
    print("* what the server's merge chooses for that path")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(
        json.dumps({"paths": rows, "round_trip": rtt, "accuracy": scores}, indent=1) + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
