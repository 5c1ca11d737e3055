"""Merge accuracy and speed on synthetic and real surfaces with known drift.

Every case writes a patch set with its truth, runs the real CLI (``mosaic-afm merge``) for each
method and scores the result:

* registration error: RMS over all patch points of the difference between where the merge puts
  each point and where it truly is, XY and Z apart, after removing the gauge that fits best (what
  no overlap sees: a rigid motion in XY, and a Z offset and plane common to all patches);
* map error: RMS of the mosaic against the true surface (after the same global transform), and
  the floor — the true transforms through the same renderer — for comparison;
* wall time and peak memory of the CLI process.

Then the default method again on further draws of texture, drift and noise of every case but the
large grid (``--draws``, 8 in all): one draw is a noisy measurement of an accuracy, so the table
gives the median, mean and worst of them, and how honest the reported per-patch sigmas are (RMS
of each patch's mean error over its sigma, XY per axis: 1 honest, below cautious, above
over-confident; the median over the draws).

With ``--sweep N`` (``make bench``: 10), the default method on N further draws of every case
but the large grid, counting gross failures (map error over 3 floors, or XY over 10 nm on a
textured case): the rare draw that eight do not show.

With ``--gratings N`` (``make bench``: 10), the edge-ramp and period sweep of TGX1-like
chessboards (:func:`grating_cases`: edge ramps of 50, 100 and 200 nm, periods of 2 and 3 µm,
steps of 0.3 and 0.6 µm, at the paper's grid and at 1 µm patches of 200 x 200 px): the default
method on N draws of each, map error over the floor (median and worst) and the XY error
against the Cramér-Rao bound of ``crb.py`` (the RMS over the draws of the merge's and of the
bound's on each draw). ``--cases none --draws 1 --no-scaling --gratings 10`` runs the sweep alone.

Prints a table and writes JSON (``--json``, default ``benchmarks/results/merge_bench.json``).
Run: ``make bench`` or
``python benchmarks/merge_bench.py [--quick] [--cases a,b] [--draws N] [--sweep N]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from backend.synthetic import patch_set_from_synth, scored, sigma_calibration
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import Chessboard, FoldedSurface, ImageSurface, Surface
from hardware.sim.synth import SynthPatch, scan_fraction, synthesize
from merge import Mosaic, Patch, PatchTransform, read_result, render_mosaic, write_patch_set

FloatArray = NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CLI = [sys.executable, "-m", "backend.cli"]


@dataclass(frozen=True)
class Case:
    name: str
    surface: Callable[[int], Surface]  # the surface of a seed (real images ignore it)
    rows: int
    cols: int
    patch_size: tuple[float, float]
    pixels: tuple[int, int]
    overlap: tuple[float, float]
    drift: DriftModel
    start: tuple[float, float] = (0.0, 0.0)
    textured: bool = True
    methods: tuple[str, ...] = ("default", "paper", "zlevel", "nominal")
    paper_iter: int = 200
    seed: int = 1

    def redrawn(self, k: int) -> Case:
        """The same case on the ``k``-th other draw of surface texture, drift and noise."""
        return dataclasses.replace(self, seed=self.seed + 1000 * k)

    @property
    def measures_speed(self) -> bool:
        """The large grid times the merge; it is not redrawn."""
        return self.rows * self.cols > 100

    def synthesize(self) -> tuple[Surface, list[SynthPatch]]:
        """The case's surface and its patch set with the truth."""
        surface = self.surface(self.seed)
        synth = synthesize(
            surface,
            rows=self.rows,
            cols=self.cols,
            patch_size=self.patch_size,
            pixels=self.pixels,
            overlap=self.overlap,
            start=self.start,
            drift=self.drift,
            seed=self.seed,
        )
        return surface, synth


def _real(name: str, pixel: tuple[float, float]) -> Callable[[int], Surface]:
    def make(seed: int) -> Surface:
        return ImageSurface(np.load(DATA / f"{name}.npy"), pixel)

    return make


def paper_grid(
    name: str, surface: Callable[[int], Surface], drift: DriftModel, seed: int = 1
) -> Case:
    """The paper's grid: 5 x 10 patches of 0.6 x 1.2 µm, 50 % / 33 % overlap, 20 nm pixels."""
    return Case(
        name,
        surface,
        rows=5,
        cols=10,
        patch_size=(0.6e-6, 1.2e-6),
        pixels=(30, 60),
        overlap=(0.5, 1 / 3),
        drift=drift,
        seed=seed,
    )


def fine_grating(name: str, surface: Callable[[int], Surface]) -> Case:
    """A grating as an AFM scans it finely: 4 x 4 patches of 1 µm in 200 x 200 pixels (5 nm),
    20 % overlap, the typical drift (no paper method: 640 000 down-sampled points)."""
    return Case(
        name,
        surface,
        rows=4,
        cols=4,
        patch_size=(1e-6, 1e-6),
        pixels=(200, 200),
        overlap=(0.2, 0.2),
        drift=DriftModel.typical(),
        methods=("default", "zlevel", "nominal"),
    )


CASES = [
    paper_grid("tgx1", lambda seed: Chessboard(seed=seed), DriftModel.typical()),
    paper_grid("folded", lambda seed: FoldedSurface(seed=seed), DriftModel.typical()),
    # a grating's flat face: 1.5 nm of roughness at about a pixel's scale is the only texture
    paper_grid("flat-rough", lambda seed: Chessboard(step=0.0, seed=seed), DriftModel.typical()),
    paper_grid("tgx1-harsh", lambda seed: Chessboard(seed=seed), DriftModel.harsh(), seed=2),
    paper_grid("folded-harsh", lambda seed: FoldedSurface(seed=seed), DriftModel.harsh(), seed=2),
    # real Nanosurf images cut into 3 x 4 overlapping patches at their own pixel pitch
    Case(
        "mos2-real",
        _real("mos2", (3.973e-6 / 512, 3.973e-6 / 256)),
        rows=3,
        cols=4,
        patch_size=(1.241e-6, 1.241e-6),
        pixels=(160, 80),
        overlap=(0.4, 0.4),
        drift=DriftModel.typical(),
        start=(0.25e-6, 0.25e-6),
    ),
    Case(
        "grid-real",
        _real("grid", (3e-6 / 256, 3e-6 / 256)),
        rows=3,
        cols=3,
        patch_size=(1.172e-6, 1.172e-6),
        pixels=(100, 100),
        overlap=(0.4, 0.4),
        drift=DriftModel.typical(),
        start=(0.3e-6, 0.3e-6),
        textured=False,
    ),
    # TGX1 scanned finely: the flat faces' 25 nm roughness is all some overlaps hold
    fine_grating("tgx1-1um", lambda seed: Chessboard(seed=seed)),
    Case(
        "grid20x20",
        lambda seed: FoldedSurface(seed=seed + 2),
        rows=20,
        cols=20,
        patch_size=(1.28e-6, 1.28e-6),
        pixels=(64, 64),
        overlap=(0.3, 0.3),
        drift=DriftModel.typical(),
        methods=("default", "zlevel", "nominal"),
    ),
]


#: The grating sweep: edge ramps (``Chessboard.edge_width``, bottom to top of an edge), periods
#: and steps of TGX1-like chessboards, metres, and the two geometries.
RAMPS = (50e-9, 100e-9, 200e-9)
PERIODS = (2e-6, 3e-6)
STEPS = (0.3e-6, 0.6e-6)
GEOMETRIES = ("paper", "1um")


def grating_case(ramp: float, period: float, step: float, geometry: str) -> Case:
    """A TGX1-like chessboard of the sweep at the paper's grid (:func:`paper_grid`) or in 1 µm
    patches (:func:`fine_grating`), the typical drift."""
    name = f"{geometry}-r{ramp * 1e9:.0f}-p{period * 1e6:g}-s{step * 1e6:g}"

    def surface(seed: int) -> Surface:
        return Chessboard(period=period, step=step, edge_width=ramp, seed=seed)

    if geometry == "paper":
        return dataclasses.replace(
            paper_grid(name, surface, DriftModel.typical()), methods=("default",)
        )
    if geometry == "1um":
        return dataclasses.replace(fine_grating(name, surface), methods=("default",))
    raise ValueError(f"unknown geometry {geometry!r}: use one of {', '.join(GEOMETRIES)}")


def grating_cases() -> list[tuple[str, float, float, float, Case]]:
    """Every case of the sweep with its geometry, ramp, period and step."""
    return [
        (geometry, ramp, period, step, grating_case(ramp, period, step, geometry))
        for geometry in GEOMETRIES
        for period in PERIODS
        for step in STEPS
        for ramp in RAMPS
    ]


def grating_row(case: Case, count: int, work: Path) -> dict[str, Any]:
    """The default method on ``count`` draws of a sweep case: map error over the floor, XY
    error, and the Cramér-Rao bound of XY on every draw (its expectation,
    :func:`crb.registration_bound`). XY against the bound: the merge's RMS over the draws
    against the bound's, both estimates of an expected square (a median of the merge's against
    the first draw's bound mixed a median with an RMS, and one draw's texture with another's)."""
    from crb import registration_bound  # a script beside this one

    runs = [default_run(case, k, work) for k in range(count)]
    bounds = []
    for k in range(count):
        surface, synth = case.redrawn(k).synthesize()
        bounds.append(registration_bound(synth, surface, case.drift)[0])
    ratio = np.array([v["map_over_floor"] for v in runs])
    xy = np.array([v["reg_xy_nm"] for v in runs])
    xy_rms, bound_rms = float(np.sqrt(np.mean(xy**2))), float(np.sqrt(np.mean(np.square(bounds))))
    return {
        "case": case.name,
        "draws": count,
        "map_over_floor_median": float(np.median(ratio)),
        "map_over_floor_worst": float(ratio.max()),
        "reg_xy_nm_median": float(np.median(xy)),
        "reg_xy_nm_rms": xy_rms,
        "crb_xy_nm": bound_rms,
        "xy_over_crb": xy_rms / bound_rms,
        "runs": runs,
    }


def map_error(
    heights: FloatArray,
    origin: tuple[float, float],
    pixel: tuple[float, float],
    surface: Surface,
    G: FloatArray,
    g: FloatArray,
) -> float:
    """RMS of the mosaic against the true surface, the mosaic taken through ``q -> G q + g``."""
    ny, nx = heights.shape
    xx, yy = np.meshgrid(origin[0] + np.arange(nx) * pixel[0], origin[1] + np.arange(ny) * pixel[1])
    ok = np.isfinite(heights)
    q = np.column_stack([xx[ok], yy[ok], heights[ok]]) @ G.T + g
    truth = surface.height(q[:, 0], q[:, 1])
    d = q[:, 2] - truth
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2)))


def true_mosaic(synth: list[SynthPatch]) -> Mosaic:
    """The drift-free heights through the true transforms and the merge's own renderer: what
    a merge that found every transform exactly would draw."""
    true_tr = [PatchTransform(s.rotation, s.translation) for s in synth]
    # the true rotations have no tilt, so the drift-free heights go through (R, t) exactly
    fixed = [
        Patch(
            id=s.id,
            heights=s.heights - s.z_drift * (scan_fraction(s.heights.shape) - 0.5),
            origin=s.origin,
            pixel_size=s.pixel_size,
        )
        for s in synth
    ]
    return render_mosaic(fixed, true_tr)


def floor_of(synth: list[SynthPatch], surface: Surface) -> float:
    """Map error (m) of the true transforms through the same renderer (:func:`true_mosaic`)."""
    mosaic = true_mosaic(synth)
    return map_error(
        mosaic.heights, mosaic.origin, mosaic.pixel_size, surface, np.eye(3), np.zeros(3)
    )


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
        score = scored(synth, [tr[s.id] for s in synth])
        exy, ez, (G, g) = score.xy, score.z, score.gauge
        m = res.mosaic
        merr = map_error(m.heights, m.origin, m.pixel_size, surface, G, g)
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


def _finite_median(values: Any) -> float:
    """Median of the finite ``values``; NaN where none is (a 1-D grating's XY sigmas: no patch's
    XY is measured along its stripes)."""
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else float("nan")


def draws(case: Case, first: dict[str, Any], count: int, work: Path) -> dict[str, Any]:
    """The default method on ``count`` draws of the case (the first one already run): one
    random draw of texture, drift and noise is a noisy measurement of an accuracy."""
    runs = [first["methods"]["default"] | {"floor_nm": first["floor_nm"]}]
    runs += [default_run(case, k, work) for k in range(1, count)]
    ratio = np.array([v["map_over_floor"] for v in runs])
    xy = np.array([v["reg_xy_nm"] for v in runs])
    z = np.array([v["reg_z_nm"] for v in runs])
    calib = np.array([[v["sigma_calibration"]["xy"], v["sigma_calibration"]["z"]] for v in runs])
    return {
        "case": case.name,
        "draws": count,
        "map_over_floor": {
            "median": float(np.median(ratio)),
            "mean": float(ratio.mean()),
            "worst": float(ratio.max()),
            "within_1_5": int((ratio <= 1.5).sum()),
        },
        "reg_xy_nm": {"median": float(np.median(xy)), "worst": float(xy.max())},
        "reg_z_nm": {"median": float(np.median(z)), "worst": float(z.max())},
        "sigma_calibration": {"xy": _finite_median(calib[:, 0]), "z": _finite_median(calib[:, 1])},
        "runs": runs,
    }


#: First draw of the robustness sweep: past every draw the benchmark's table uses.
SWEEP_FIRST = 21
#: A sweep draw fails grossly when its map error exceeds this many floors, or (on a textured
#: case) its registration error this many nanometres in XY.
GROSS_MAP, GROSS_XY_NM = 3.0, 10.0


def sweep(case: Case, count: int, work: Path) -> dict[str, Any]:
    """The default method on ``count`` further draws, counting gross failures: the rare draw
    (a wrong correlation peak in the start, a patch the refinement cannot bring back) that a
    table of eight does not show."""
    runs = []
    for k in range(SWEEP_FIRST, SWEEP_FIRST + count):
        v = default_run(case, k, work)
        gross = v["map_over_floor"] > GROSS_MAP or (case.textured and v["reg_xy_nm"] > GROSS_XY_NM)
        runs.append(
            {
                "draw": k,
                "map_over_floor": v["map_over_floor"],
                "reg_xy_nm": v["reg_xy_nm"],
                "gross": bool(gross),
            }
        )
    ratio = np.array([v["map_over_floor"] for v in runs])
    return {
        "case": case.name,
        "draws": count,
        "gross": [v["draw"] for v in runs if v["gross"]],
        "within_1_5": int((ratio <= 1.5).sum()),
        "map_over_floor_median": float(np.median(ratio)),
        "runs": runs,
    }


def scaling(work: Path, sides: tuple[int, ...] = (5, 10, 14, 20)) -> list[dict[str, Any]]:
    """CLI wall time and peak memory of the default merge against the number of patches."""
    surface = FoldedSurface(seed=3)
    rows = []
    for side in sides:
        synth = synthesize(
            surface,
            rows=side,
            cols=side,
            patch_size=(1.28e-6, 1.28e-6),
            pixels=(64, 64),
            overlap=(0.3, 0.3),
            drift=DriftModel.typical(),
            seed=1,
        )
        ps = patch_set_from_synth(synth)
        folder = work / f"scaling-{side}"
        write_patch_set(ps, folder)
        wall, peak, _ = run_cli(
            [
                "merge",
                str(folder / "manifest.json"),
                "--out",
                str(folder / "out"),
                "--quiet",
                "--no-preview",
            ]
        )
        rows.append(
            {
                "patches": side * side,
                "wall_s": wall,
                "peak_mib": peak,
                "ms_per_patch": 1e3 * wall / (side * side),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", help="comma-separated case names (default: all)")
    parser.add_argument("--quick", action="store_true", help="skip the paper method")
    parser.add_argument("--no-scaling", action="store_true", help="skip the time-vs-patches run")
    parser.add_argument(
        "--draws",
        type=int,
        default=8,
        help="draws of texture, drift and noise per paper-grid and real case (default 8; 1: none)",
    )
    parser.add_argument(
        "--sweep",
        type=int,
        default=0,
        help=f"further draws per paper-grid and real case, from draw {SWEEP_FIRST}, counting gross "
        "failures (default 0: none)",
    )
    parser.add_argument(
        "--gratings",
        type=int,
        default=0,
        help="draws per case of the edge-ramp and period sweep of chessboards (default 0: none)",
    )
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "merge_bench.json"))
    args = parser.parse_args(argv)
    chosen = [c for c in CASES if not args.cases or c.name in args.cases.split(",")]
    results = []
    header = (
        f"{'case':<13}{'method':<9}{'reg XY nm':>10}{'reg Z nm':>10}{'map nm':>9}"
        f"{'floor nm':>9}{'map/floor':>10}{'wall s':>8}{'peak MiB':>9}{'iter':>6}  unconstr."
    )
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as tmp:
        for case in chosen:
            if args.quick:
                case = Case(
                    **{**case.__dict__, "methods": tuple(m for m in case.methods if m != "paper")}
                )
            r = run_case(case, Path(tmp))
            results.append(r)
            for method, v in r["methods"].items():
                print(
                    f"{r['case']:<13}{method:<9}{v['reg_xy_nm']:>10.2f}{v['reg_z_nm']:>10.2f}"
                    f"{v['map_nm']:>9.2f}{r['floor_nm']:>9.2f}{v['map_over_floor']:>10.2f}"
                    f"{v['wall_s']:>8.2f}{v['peak_mib']:>9.0f}{v['iterations']:>6}"
                    f"  {v['xy_unconstrained_patches']}",
                    flush=True,
                )
        spread = []
        if args.draws > 1:
            print(
                f"\ndefault method over {args.draws} draws of texture, drift and noise"
                f"\n{'case':<13}{'map/floor median':>17}{'mean':>7}{'worst':>7}{'<= 1.5':>8}"
                f"{'XY nm med':>10}{'worst':>7}{'Z nm med':>9}{'worst':>7}{'err/σ XY':>10}{'Z':>6}"
            )
            for case, r in zip(chosen, results, strict=True):
                if case.measures_speed:
                    continue
                d = draws(case, r, args.draws, Path(tmp))
                spread.append(d)
                m, xy, z = d["map_over_floor"], d["reg_xy_nm"], d["reg_z_nm"]
                cal = d["sigma_calibration"]
                print(
                    f"{case.name:<13}{m['median']:>17.2f}{m['mean']:>7.2f}{m['worst']:>7.2f}"
                    f"{m['within_1_5']:>5}/{d['draws']:<2}{xy['median']:>10.2f}{xy['worst']:>7.2f}"
                    f"{z['median']:>9.2f}{z['worst']:>7.2f}{cal['xy']:>10.2f}{cal['z']:>6.2f}",
                    flush=True,
                )
        swept = []
        if args.sweep > 0:
            print(
                f"\nrobustness: default method on {args.sweep} further draws (from draw "
                f"{SWEEP_FIRST}); gross = map > {GROSS_MAP:g} x floor or XY > {GROSS_XY_NM:g} nm"
                f"\n{'case':<13}{'map/floor median':>17}{'<= 1.5':>8}{'gross':>7}  draws"
            )
            for case in chosen:
                if case.measures_speed:
                    continue
                sw = sweep(case, args.sweep, Path(tmp))
                swept.append(sw)
                print(
                    f"{case.name:<13}{sw['map_over_floor_median']:>17.2f}"
                    f"{sw['within_1_5']:>5}/{sw['draws']:<2}{len(sw['gross']):>7}  "
                    f"{', '.join(str(k) for k in sw['gross']) or '-'}",
                    flush=True,
                )
        gratings = []
        if args.gratings > 0:
            print(
                f"\nTGX1-like chessboards: default method over {args.gratings} draws each"
                f"\n{'geometry':<9}{'ramp nm':>8}{'period µm':>10}{'step µm':>8}"
                f"{'map/floor med':>14}{'worst':>7}{'XY nm rms':>10}{'CRB XY nm':>10}{'XY/CRB':>8}"
            )
            for geometry, ramp, period, step, case in grating_cases():
                g = grating_row(case, args.gratings, Path(tmp))
                where = {"geometry": geometry, "ramp": ramp, "period": period, "step": step}
                gratings.append(g | where)
                print(
                    f"{geometry:<9}{ramp * 1e9:>8.0f}{period * 1e6:>10g}{step * 1e6:>8g}"
                    f"{g['map_over_floor_median']:>14.2f}{g['map_over_floor_worst']:>7.2f}"
                    f"{g['reg_xy_nm_rms']:>10.2f}{g['crb_xy_nm']:>10.2f}{g['xy_over_crb']:>8.2f}",
                    flush=True,
                )
        print(f"\n{'patches (64 x 64 px)':<22}{'wall s':>8}{'ms/patch':>10}{'peak MiB':>10}")
        scale_rows = [] if args.no_scaling else scaling(Path(tmp))
        for row in scale_rows:
            print(
                f"{row['patches']:<22}{row['wall_s']:>8.2f}{row['ms_per_patch']:>10.1f}"
                f"{row['peak_mib']:>10.0f}",
                flush=True,
            )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "merge": results,
        "draws": spread,
        "sweep": swept,
        "gratings": gratings,
        "scaling": scale_rows,
    }
    Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
