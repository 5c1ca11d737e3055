"""A benchmark case through the real CLI (``mosaic-afm merge``) in a fresh process, scored
against its truth: registration and map error (beside the floor), wall time and peak memory of
the process, iterations, the patches left unconstrained and how honest their sigmas are. Used
by ``merge_bench.py``."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from backend.synthetic import patch_set_from_synth, sigma_calibration
from merge import read_result, write_patch_set

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cases import ROOT, Case, floor_of, scored_merge  # a module beside this script

CLI = [sys.executable, "-m", "backend.cli"]


def run_cli(args: list[str]) -> tuple[float, float, str]:
    """Run the CLI; return wall seconds, peak RSS (MiB) of that process and its stdout."""
    start = time.perf_counter()
    proc = subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    out = proc.stdout.read().decode() if proc.stdout else ""
    err = proc.stderr.read().decode() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"CLI failed: {' '.join(args)}\n{err}")
    return wall, usage.ru_maxrss / 1024.0, out.strip()


def run_case(case: Case, work: Path) -> dict[str, Any]:
    surface, synth = case.synthesize()
    ps = patch_set_from_synth(synth)
    folder = work / case.name
    write_patch_set(ps, folder / "patches")
    floor = floor_of(synth, surface)
    rows = {}
    for method in case.methods:
        out = folder / method
        args = [
            "merge",
            str(folder / "patches" / "manifest.json"),
            "--out",
            str(out),
            "--method",
            method,
            "--quiet",
            "--no-preview",
        ]
        if method == "paper":
            args += ["--max-iter", str(case.paper_iter)]
        wall, peak, _ = run_cli(args)
        res = read_result(out)
        tr = res.transforms
        score, merr = scored_merge(synth, [tr[s.id] for s in synth], res.mosaic, surface)
        exy, ez = score.xy, score.z
        unconstrained = sum(not p["xy_constrained"] for p in res.document["patches"])
        reports = {p["id"]: p for p in res.document["patches"]}
        sigmas = np.array(
            [[_finite(reports[s.id]["xy_sigma"]), _finite(reports[s.id]["z_sigma"])] for s in synth]
        )
        errors = score.patches
        rows[method] = {
            "reg_xy_nm": exy * 1e9,
            "reg_z_nm": ez * 1e9,
            "map_nm": merr * 1e9,
            "map_over_floor": merr / floor,
            "wall_s": wall,
            "peak_mib": peak,
            "iterations": res.document["iterations"],
            "converged": res.document["converged"],
            "xy_unconstrained_patches": unconstrained,
            "sigma_calibration": sigma_calibration(errors, sigmas[:, 0], sigmas[:, 1]),
        }
    return {
        "case": case.name,
        "patches": len(synth),
        "pixels": list(case.pixels),
        "textured": case.textured,
        "floor_nm": floor * 1e9,
        "methods": rows,
    }


def _finite(value: float | None) -> float:
    """A sigma from ``mosaic.json`` (null where no data constrain it)."""
    return float("inf") if value is None else float(value)


def default_run(case: Case, k: int, work: Path) -> dict[str, Any]:
    """The default method's row on the ``k``-th draw of ``case``, with the draw's floor."""
    r = run_case(dataclasses.replace(case.redrawn(k), methods=("default",)), work)
    return dict(r["methods"]["default"]) | {"floor_nm": r["floor_nm"]}
