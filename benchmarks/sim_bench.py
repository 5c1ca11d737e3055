"""Simulated instrument speed: patches per wall second at maximum simulated speed.

Scans snake-ordered mosaics on the simulated AFM-in-SEM through the real drivers and
procedures (move, land, scan, retract) and prints patches per wall second, for 30 x 60 and
256 x 256 pixel patches. Target: 50 patches of 30 x 60 in under 20 s on 2 cores.
Writes JSON to ``benchmarks/results/sim_bench.json`` (or ``--json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from hardware.sim.instrument import SimulatedAFM
from hardware.sim.mosaic import scan_mosaic
from hardware.sim.surfaces import Chessboard

ROOT = Path(__file__).resolve().parents[1]
CASES = [
    # name, rows, cols, pixels, patch size, line rate (Hz): slow enough for the force loop
    ("50 x (30 x 60)", 5, 10, (30, 60), (0.6e-6, 1.2e-6), 2.0),
    ("4 x (256 x 256)", 2, 2, (256, 256), (1.2e-6, 1.2e-6), 0.5),
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "sim_bench.json"))
    args = parser.parse_args(argv)
    rows: list[dict[str, Any]] = []
    print(f"{'case':<18}{'patches':>8}{'wall s':>9}{'patches/s':>11}{'simulated s':>13}")
    for name, r, c, pixels, size, line_rate in CASES:
        with SimulatedAFM(Chessboard(seed=1), seed=1) as afm:
            start = time.perf_counter()
            scanned = scan_mosaic(
                afm,
                rows=r,
                cols=c,
                patch_size=size,
                pixels=pixels,
                overlap=(0.5, 1 / 3),
                line_rate=line_rate,
            )
            wall = time.perf_counter() - start
            simulated = afm.clock.now()
        n = len(scanned)
        rows.append(
            {
                "case": name,
                "patches": n,
                "wall_s": wall,
                "patches_per_s": n / wall,
                "simulated_s": simulated,
            }
        )
        print(f"{name:<18}{n:>8}{wall:>9.2f}{n / wall:>11.2f}{simulated:>13.0f}", flush=True)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"sim": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
