"""The Nanonis path against sim://: patches per wall second, and command round trips.

Scans the same snake-ordered mosaic on the same simulated world twice at maximum simulated
speed: once on ``sim://`` (the software rasters the robot's fine axes over MCS links), once on
``nanonis://...?stage=mcs:...`` (the Nanonis simulator's scan generator, its TCP protocol and
the MCS stage), through the same procedures the server runs (move, prepare, land, scan,
retract). Prints patches per wall second, the ratio per patch (target: Nanonis at most 1.5 x
sim://), and the round trip of a Nanonis command on loopback (p50, p99). Writes JSON to
``benchmarks/results/nanonis_bench.json`` (or ``--json``).
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
from hardware.procedures import move_stage, retract
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.surfaces import Chessboard

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
) -> int:
    """Every patch of the grid, as the runner does it; returns how many were scanned."""
    _, loop, scanner = m.require_afm()
    plan = snake_grid(rows, cols, patch_size=size, overlap=(0.5, 1 / 3))
    for planned in plan:
        move_stage(m.stage_x, m.stage_y, m.robot_x, m.robot_y, origin=planned.origin, size=size)
        scanner.prepare(size=size, pixels=pixels)
        m.land()
        scanner.scan(size=size, pixels=pixels, line_rate=line_rate)
        retract(m.robot_z, loop)
    return len(plan)


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
                n = scan_all(m, r, c, pixels, size, line_rate)
                walls[path] = time.perf_counter() - start
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
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"paths": rows, "round_trip": rtt}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
