"""A benchmark case through the real CLI (``mosaic-afm merge``) in a fresh process, scored
against its truth: registration and map error (beside the floor), wall time and peak memory of
the process, iterations, the patches left unconstrained and how honest their sigmas are. Used
by ``merge_bench.py``."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from backend.synthetic import patch_set_from_synth, sigma_calibration
from merge import read_result, write_patch_set
from merge.report.verdict import REGISTERING

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cases import ROOT, Case, floor_of, scored_merge  # a module beside this script

CLI = [sys.executable, "-m", "backend.cli"]
#: A patch the report holds (``xy_constrained``) this far off (metres), and more than
#: SILENT_SIGMAS of its own XY sigma, is a silent failure (as ``merge_variations.py`` counts).
SILENT = 10e-9
SILENT_SIGMAS = 3.0


#: A small process that runs the CLI as its child and reports the child's wall time and peak
#: memory as the last line of its stderr. Linux starts a forked child's resident high-water
#: mark at its parent's size and keeps it over the exec, so the CLI forked from the bench
#: itself "peaked" at the bench's size (394 MiB for every grating run, where the CLI alone
#: takes 89); forked from this one it starts at some 10 MiB, far below any merge's.
LAUNCH = """
import os, subprocess, sys, time
start = time.perf_counter()
child = subprocess.Popen(sys.argv[1:])
_, status, usage = os.wait4(child.pid, 0)
sys.stderr.write(f"\\n{time.perf_counter() - start!r} {usage.ru_maxrss}\\n")
sys.exit(os.waitstatus_to_exitcode(status))
"""


#: The merge's exit code for a mosaic written but not to be trusted (its verdict says why).
UNTRUSTED = 3


def run_cli(args: list[str], *, accept: tuple[int, ...] = (0,)) -> tuple[float, float, str]:
    """Run the CLI (through :data:`LAUNCH`); return its wall seconds, its own peak RSS (MiB)
    and its stdout. An exit code outside ``accept`` raises."""
    proc = subprocess.run(
        [sys.executable, "-c", LAUNCH, *CLI, *args], capture_output=True, cwd=ROOT, check=False
    )
    err = proc.stderr.decode().rstrip().splitlines()
    said = err[-1].split() if err else []
    if proc.returncode not in accept or len(said) != 2:
        told = err[:-1] if len(said) == 2 else err  # the CLI's own message, not the launcher's
        raise RuntimeError(f"CLI failed: {' '.join(args)}\n" + "\n".join(told))
    return float(said[0]), int(said[1]) / 1024.0, proc.stdout.decode().strip()


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
        # a mosaic flagged untrusted is a result too: the verdict said so, never silent
        wall, peak, told = run_cli(args, accept=(0, UNTRUSTED))
        res = read_result(out)
        tr = res.transforms
        reports = {p["id"]: p for p in res.document["patches"]}
        held = np.array([reports[s.id]["xy_constrained"] for s in synth])
        # a method that registers XY is judged on the patches its report holds; one that does
        # not (zlevel, nominal) measured no place, and its report's "held" says only what the
        # overlaps could have pinned
        gauged = held if method in REGISTERING else None
        score, merr = scored_merge(
            synth, [tr[s.id] for s in synth], res.mosaic, surface, held=gauged
        )
        exy, ez = score.xy, score.z
        unconstrained = int((~held).sum())
        sigmas = np.array(
            [[_finite(reports[s.id]["xy_sigma"]), _finite(reports[s.id]["z_sigma"])] for s in synth]
        )
        errors = score.patches
        off = np.hypot(errors[:, 0], errors[:, 1])
        cols = np.array([s.col for s in synth])
        ends = (cols == cols.min()) | (cols == cols.max())  # the snake's rows end there
        silent = held & (off > SILENT) & (off > SILENT_SIGMAS * sigmas[:, 0])
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
            # the worst patch at a row's end over the median patch (issue 66: at most 2)
            "row_end_over_median": float(off[ends].max() / max(np.median(off), 1e-15)),
            # patches held (xy_constrained) yet off by more than SILENT and SILENT_SIGMAS
            # of their own sigma: a failure the report does not say
            "silent_patches": int(silent.sum()),
            "trusted": not told.splitlines()[-1].startswith("NOT TRUSTED") if told else True,
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
