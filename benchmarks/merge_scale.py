"""The merge at scale: time, peak memory, iterations and accuracy from 100 to 10,000 patches
(issue: the merge at scale).

Folded surface, 1 µm patches of 64 x 64 px at 25 % overlap (``--big``: also 2,500 patches of
256 x 256 px), the typical drift. For every size the patch set is written as the CLI reads it
(``manifest.json`` and one ``.npy`` per patch); the CLI's own code (``mosaic-afm merge``,
preview included) then runs in a fresh process, so its peak memory is its own. Before it
merges the mosaic, that process merges four patches: what any merging process holds once
(BLAS's and the thread pool's buffers, the sparse solver's, the lazily imported modules: a
fixed cost, ``fixed MB``) is then in its resident memory. The peak over that, per input pixel,
is the merge's bytes per input pixel (target <= 60); ``B/px all`` counts the fixed cost too
(the peak over the memory after the imports). The result is scored against the truth:
registration error (every measured point against its true place, after the gauge: a rigid
motion in XY, a Z offset and plane; every 4th point along both axes from 1,600 patches up) and
map error (the mosaic against the true surface, same gauge; every few mosaic pixels on the
large ones), and the floor (the map error of the true transforms through the same renderer,
scored the same way; ``map/floor`` their ratio: 1 is a merge that found every transform
exactly). The time of each size against that of 400 patches, beside the ratio of patches, says
whether the time is linear (equal ratios). ``--bound``: beside the merge, the Cramér-Rao bound
of each size up to :data:`BOUND_MAX` patches (``crb.py``, the simulator's drift as the drift
planes' prior): the XY and Z errors and map/floor an efficient merge would have;
``--oracle``, at every size, the heights an oracle would merge to (:func:`oracle_of`). A large
mosaic's map/floor is above 1 by physics too: the scan lines' offsets leave the patch rows'
relative tilts weakly measured, and that mosaic-wide bend grows with the mosaic. ``Z rows`` is
the part of the Z error the mosaic's rows of patches hold in common (RMS over the patches of
their row's mean Z error): where it is most of ``Z``, the error is that bend (900 patches of
256 x 256 px, one draw: Z 0.71 nm, of it 0.70 the rows' common offsets, 0.10 left within the
rows; the rows' offsets the running sum of their common tilt about x). ``err/σ`` is how honest
the report's uncertainties are at that size: the RMS over the patches of each one's error (its
mean, after the gauge) over its reported sigma, per axis in XY and in Z (1 honest, above
over-confident). ``cancel s``
is how long a cancel could wait: the merge is handed a cancel that never fires, and the longest
time between two of its looks is timed (start to the first look and the last look to the end
included).

Prints a table and writes JSON (``--json``, default ``benchmarks/results/merge_scale.json``).
Run: ``python benchmarks/merge_scale.py [--sides 10,20,30,40] [--pixels 64] [--large] [--big]
[--bound] [--oracle] [--line-noise NM] [--sample sparse]`` (``--large``: also 2,500 and
10,000 patches of 64 x 64 px; ``--sample sparse``: a folded surface whose folds lie a few µm
apart, so most overlaps hold roughness alone; ``--pixels``: the ``--sides`` mosaics' patches
that many pixels a side; ``--line-noise``: the scan lines' offsets, RMS nm, instead of the
typical 0.3: at 0 what is left of a large mosaic's bend is the white noise's and the drift's).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_cases import map_error, true_mosaic, true_places  # a module beside this script

ROOT = Path(__file__).resolve().parents[1]
#: Patch side, metres, and overlap of every case (the issue's measurements).
PATCH_SIDE = 1e-6
OVERLAP = 0.25
#: Patches up to which ``--bound`` computes the Cramér-Rao bound (its line offsets' system and
#: dense covariance grow with the mosaic: 400 patches of 256 x 256 px take six minutes).
BOUND_MAX = 400


def _memory(field: str) -> int:
    """Bytes of ``VmRSS`` (now) or ``VmHWM`` (the peak) of this process, from /proc: unlike
    ``ru_maxrss``, which Linux carries over an exec from the parent, they are this program's."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


class _Looks:
    """A cancel that never fires and times the merge's looks at it: the longest wait between
    two (what a cancel could wait)."""

    def __init__(self) -> None:
        self.last: float | None = None
        self.longest = 0.0

    def __call__(self) -> bool:
        now = time.perf_counter()
        if self.last is not None:
            self.longest = max(self.longest, now - self.last)
        self.last = now
        return False

    def wrap(self, run: Any) -> Any:
        def run_listened(*args: Any, **kwargs: Any) -> Any:
            self.last = time.perf_counter()
            out = run(*args, cancel=self, **kwargs)
            self()
            return out

        return run_listened


def child(manifest: str, out: str, warm: str) -> int:
    """Run the CLI's merge in this process, after a merge of the small patch set ``warm``; print
    its wall time, memory and longest wait for a cancel as JSON."""
    import merge
    from backend.cli import main as cli_main

    base = _memory("VmRSS")
    if cli_main(["merge", warm, "--out", out + "-warm", "--quiet"]) != 0:
        return 1
    warmed = _memory("VmRSS")
    looks = _Looks()
    merge.run = looks.wrap(merge.run)  # the CLI's merge, given a cancel
    clock = time.perf_counter()
    code = cli_main(["merge", manifest, "--out", out, "--quiet"])
    wall = time.perf_counter() - clock
    peak = _memory("VmHWM")
    said = {"code": code, "wall_s": wall, "base_bytes": base, "warm_bytes": warmed}
    print(json.dumps(said | {"peak_bytes": peak, "cancel_wait_s": looks.longest}))
    return code


def _warm_set(work: Path, pixels: int) -> Path:
    """Four patches of ``pixels`` px a side, written once per run (the warm-up merge's)."""
    from backend.synthetic import patch_set_from_synth
    from hardware.sim.drift import DriftModel
    from hardware.sim.surfaces import FoldedSurface
    from hardware.sim.synth import synthesize
    from merge.io.manifest import write_patch_set

    folder = work / f"warm-{pixels}"
    if not (folder / "manifest.json").exists():
        synth = synthesize(
            FoldedSurface(seed=4),
            rows=2,
            cols=2,
            patch_size=(PATCH_SIDE, PATCH_SIDE),
            pixels=(pixels, pixels),
            overlap=(OVERLAP, OVERLAP),
            drift=DriftModel.typical(),
            seed=2,
        )
        write_patch_set(patch_set_from_synth(synth), folder)
    return folder / "manifest.json"


def _merge_in_child(manifest: Path, out: Path, warm: Path) -> dict[str, Any]:
    proc = subprocess.run(
        [sys.executable, __file__, "--child", str(manifest), str(out), str(warm)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"the merge failed:\n{proc.stdout}\n{proc.stderr}")
    said: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return said


def drift_planes_prior(synth: Any, drift: Any) -> tuple[float, float]:
    """The simulator's own drift as the drift planes' prior (x, y; metres, the planes' rise
    from a patch's centre to its corner): a drift in time over the patch, across the lines
    all of it, along a line one line's share."""
    s = synth[0]
    ny, nx = s.heights.shape
    side = np.array([nx, ny]) * s.pixel_size  # metres
    radius = 0.5 * float(np.hypot(*side))
    rise = drift.z_drift_sigma * radius / side
    return float(rise[0]) / ny, float(rise[1])


def bound_of(synth: Any, surface: Any, drift: Any, *, samples: int = 8) -> dict[str, float]:
    """What an efficient merge could reach on this patch set (:mod:`cramer_rao`): the
    Cramér-Rao bound with the simulator's own drift as the drift planes' prior
    (:func:`drift_planes_prior`), its expected XY and Z errors and the spread of its map error
    over the floor (``samples`` draws of corrections from it)."""
    import cramer_rao  # a module beside this script

    prior = drift_planes_prior(synth, drift)
    r = cramer_rao.efficient_errors(synth, surface, drift, samples=samples, plane_prior=prior)
    return {f"bound_{k}": v for k, v in r.items()}


def oracle_of(synth: Any, surface: Any, drift: Any, *, stride: int, floor: float) -> dict[str, Any]:
    """The heights an oracle would merge to, on sizes beyond the bound's reach: the heights'
    last solve (:func:`merge.refine.heights.solve_heights`, every patch's Z offset and drift
    plane with every scan line's offset) at the TRUE places, with the simulator's own noise,
    line offsets and drift as its statistics and prior, every row weighed alike. Its Z error
    is one draw of what the data tell of the heights once every XY is known (the posterior
    mean of a linear Gaussian model: no merge does better on average); its map over the floor
    says how far above the floor the line offsets alone leave a mosaic."""
    from backend.synthetic import patch_set_from_synth, scored
    from merge import render_mosaic
    from merge.core.overlap import overlapping_pairs
    from merge.refine.heights import solve_heights
    from merge.refine.line_statistics import LineStatistics

    patches = patch_set_from_synth(synth).patches
    truth = true_places(synth)
    # the nominal footprints, grown by the stage's errors: a pair that does not meet has no rows
    pairs = overlapping_pairs(
        np.array([p.footprint for p in patches]), margin=4 * drift.stage_sigma
    )
    known = LineStatistics(math.inf, drift.noise, drift.line_noise, 0.0)
    solved = solve_heights(
        patches, truth, pairs, plane_sigma=drift_planes_prior(synth, drift), statistics=known
    )
    if solved is None:  # no line offsets: the true places are the oracle
        return {}
    score = scored(synth, solved.transforms, stride=stride)
    G, g = score.gauge
    mosaic = render_mosaic(patches, solved.transforms)
    merr = map_error(mosaic.heights, mosaic.origin, mosaic.pixel_size, surface, G, g, stride=stride)
    return {
        "oracle_reg_z_nm": score.z * 1e9,
        "oracle_reg_z_rows_nm": row_error(score.patches[:, 2], synth) * 1e9,
        "oracle_map_over_floor": merr / floor,
    }


def row_error(z: Any, synth: Any) -> float:
    """RMS (over the patches) of the mean Z error of each patch's row of the mosaic: the share
    of the Z error that the rows hold in common (``z`` (n,), every patch's mean Z error)."""
    rows = np.array([s.row for s in synth])
    means = np.bincount(rows, weights=z) / np.bincount(rows)
    return float(np.sqrt(np.mean(means[rows] ** 2)))


#: The samples, by the correlation length of the field whose zero lines are the folds'
#: crests (metres): the folded surface, dense (a fold every few hundred nm), and one whose
#: folds are sparse (a few µm apart: most overlaps hold the 1 nm roughness alone, issue 66).
SAMPLES = {"folded": 350e-9, "sparse": 2e-6}


def one_size(
    side: int,
    pixels: int,
    work: Path,
    *,
    bound: bool = False,
    oracle: bool = False,
    line_noise: float | None = None,
    sample: str = "folded",
) -> dict[str, Any]:
    """Synthesise, merge (in a fresh process) and score a ``side`` x ``side`` mosaic; with
    ``bound``, also its Cramér-Rao bound (:func:`bound_of`), with ``oracle`` the heights' solve
    at the true places (:func:`oracle_of`). ``line_noise``: the scan lines' offsets (RMS,
    metres) instead of the typical drift's. ``sample``: :data:`SAMPLES`."""
    from backend.synthetic import patch_set_from_synth, scored, sigma_calibration
    from hardware.sim.drift import DriftModel
    from hardware.sim.surfaces import FoldedSurface
    from hardware.sim.synth import synthesize
    from merge.core.transforms import PatchTransform
    from merge.io.manifest import write_patch_set

    surface = FoldedSurface(seed=3, fold_length=SAMPLES[sample])
    drift = DriftModel.typical()
    if line_noise is not None:
        drift = dataclasses.replace(drift, line_noise=line_noise)
    synth = synthesize(
        surface,
        rows=side,
        cols=side,
        patch_size=(PATCH_SIDE, PATCH_SIDE),
        pixels=(pixels, pixels),
        overlap=(OVERLAP, OVERLAP),
        drift=drift,
        seed=1,
    )
    folder = work / f"{sample}-{side}x{side}-{pixels}"
    manifest = write_patch_set(patch_set_from_synth(synth), folder / "patches")
    out = folder / "out"
    ran = _merge_in_child(manifest, out, _warm_set(work, pixels))
    doc = json.loads((out / "mosaic.json").read_text())
    by_id = {
        p["id"]: PatchTransform(
            p["transform"]["rotation"],
            p["transform"]["translation"],
            p["transform"]["z_slope"],
            p["transform"]["centre"],
        )
        for p in doc["patches"]
    }
    n = side * side
    stride = 1 if n * pixels**2 < 5_000_000 else 4
    transforms = [by_id[s.id] for s in synth]
    score = scored(synth, transforms, stride=stride)
    exy, ez, (G, g), errors = score.xy, score.z, score.gauge, score.patches
    ez_rows = row_error(errors[:, 2], synth)
    sigmas = np.array([[p["xy_sigma"], p["z_sigma"]] for p in doc["patches"]], dtype=float)
    honest = sigma_calibration(errors, *sigmas.T)
    heights = np.load(out / "mosaic.npy", mmap_mode="r")
    origin = (float(doc["origin"][0]), float(doc["origin"][1]))
    pixel = (float(doc["pixel_size"][0]), float(doc["pixel_size"][1]))
    merr = map_error(heights, origin, pixel, surface, G, g, stride=stride)
    del heights  # the floor's mosaic is drawn next: one at a time
    truth = true_mosaic(synth)
    floor = map_error(
        truth.heights,
        truth.origin,
        truth.pixel_size,
        surface,
        np.eye(3),
        np.zeros(3),
        stride=stride,
    )
    input_pixels = n * pixels * pixels
    extra = bound_of(synth, surface, drift) if bound else {}
    if oracle:
        extra |= oracle_of(synth, surface, drift, stride=stride, floor=floor)
    return extra | {
        "patches": n,
        "pixels": pixels,
        "line_noise_nm": drift.line_noise * 1e9,
        "wall_s": ran["wall_s"],
        "iterations": doc["iterations"],
        "converged": doc["converged"],
        "timings": doc["timings"],
        "peak_gb": ran["peak_bytes"] / 1e9,
        "bytes_per_pixel": (ran["peak_bytes"] - ran["warm_bytes"]) / input_pixels,
        "bytes_per_pixel_all": (ran["peak_bytes"] - ran["base_bytes"]) / input_pixels,
        "fixed_mb": (ran["warm_bytes"] - ran["base_bytes"]) / 1e6,
        "cancel_wait_s": ran["cancel_wait_s"],
        "reg_xy_nm": exy * 1e9,
        "reg_z_nm": ez * 1e9,
        "reg_z_rows_nm": ez_rows * 1e9,
        "sigma_calibration": honest,
        "map_nm": merr * 1e9,
        "floor_nm": floor * 1e9,
        "scored_every": stride,
        "mosaic_shape": doc["shape"],
    }


def _reference(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The size every time is compared with: 400 patches of 64 x 64 px, if it ran."""
    return next((r for r in rows if r["patches"] == 400 and r["pixels"] == 64), None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides", default="10,20,30,40", help="mosaic sides (patches per row)")
    parser.add_argument(
        "--pixels", type=int, default=64, help="pixels a side of the --sides patches (default 64)"
    )
    parser.add_argument(
        "--line-noise",
        type=float,
        metavar="NM",
        help="the scan lines' offsets, RMS nm (default the typical drift's 0.3; 0 shows what a "
        "large mosaic's bend owes them)",
    )
    parser.add_argument(
        "--sample",
        choices=sorted(SAMPLES),
        default="folded",
        help="the folded surface (default) or one whose folds are sparse",
    )
    parser.add_argument("--large", action="store_true", help="also 50 x 50 and 100 x 100")
    parser.add_argument("--big", action="store_true", help="also 50 x 50 patches of 256 x 256")
    parser.add_argument(
        "--bound",
        action="store_true",
        help=f"also the Cramér-Rao bound of the sizes up to {BOUND_MAX} patches (minutes each)",
    )
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="also the heights' solve at the true places with the simulator's statistics, at "
        "every size (what the line offsets alone leave above the floor)",
    )
    parser.add_argument(
        "--child", nargs=3, metavar=("MANIFEST", "OUT", "WARM"), help=argparse.SUPPRESS
    )
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "merge_scale.json"))
    args = parser.parse_args(argv)
    if args.child:
        return child(*args.child)
    try:
        sizes = [(int(s), args.pixels) for s in args.sides.split(",") if s.strip()]
    except ValueError:
        parser.error(f"--sides must be integers separated by commas, got {args.sides!r}")
    if any(side < 2 for side, _ in sizes) or args.pixels < 8:
        # a mosaic of one patch has nothing to merge
        parser.error(f"need sides >= 2 and --pixels >= 8, got {args.sides!r} and {args.pixels}")
    if args.line_noise is not None and not 0 <= args.line_noise < math.inf:
        parser.error(f"--line-noise must be >= 0 nm and finite, got {args.line_noise}")
    line_noise = None if args.line_noise is None else args.line_noise * 1e-9
    if args.large:
        sizes += [(50, 64), (100, 64)]
    if args.big:
        sizes += [(50, 256)]
    rows = []
    print(
        f"{'patches':>8}{'px':>5}{'wall s':>9}{'iter':>6}{'peak GB':>9}{'B/px':>7}"
        f"{'B/px all':>9}{'fixed MB':>9}{'XY nm':>8}{'Z nm':>7}{'Z rows':>7}{'map nm':>8}"
        f"{'floor':>7}{'map/floor':>10}{'err/σ XY':>9}{'Z':>5}"
        f"{'t/t400':>8}{'n/n400':>8}{'cancel s':>9}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for side, pixels in sizes:
            r = one_size(
                side,
                pixels,
                Path(tmp),
                bound=args.bound and side * side <= BOUND_MAX,
                oracle=args.oracle,
                line_noise=line_noise,
                sample=args.sample,
            )
            rows.append(r)
            ref = _reference(rows)
            ratio = r["wall_s"] / ref["wall_s"] if ref else float("nan")
            r["patch_ratio_400"] = r["patches"] / 400
            print(
                f"{r['patches']:>8}{pixels:>5}{r['wall_s']:>9.1f}{r['iterations']:>6}"
                f"{r['peak_gb']:>9.2f}{r['bytes_per_pixel']:>7.0f}"
                f"{r['bytes_per_pixel_all']:>9.0f}{r['fixed_mb']:>9.0f}{r['reg_xy_nm']:>8.2f}"
                f"{r['reg_z_nm']:>7.2f}{r['reg_z_rows_nm']:>7.2f}{r['map_nm']:>8.2f}"
                f"{r['floor_nm']:>7.2f}{r['map_nm'] / r['floor_nm']:>10.3f}"
                f"{r['sigma_calibration']['xy']:>9.2f}{r['sigma_calibration']['z']:>5.2f}"
                f"{ratio:>8.2f}{r['patch_ratio_400']:>8.2f}{r['cancel_wait_s']:>9.2f}",
                flush=True,
            )
            if "bound_reg_z_nm" in r:
                print(
                    f"{'':>13}bound: XY {r['bound_reg_xy_nm']:.2f} nm, Z {r['bound_reg_z_nm']:.2f} "
                    f"nm, map/floor median {r['bound_map_over_floor_median']:.3f} (90th "
                    f"percentile {r['bound_map_over_floor_p90']:.3f})",
                    flush=True,
                )
            if "oracle_reg_z_nm" in r:
                print(
                    f"{'':>13}oracle: Z {r['oracle_reg_z_nm']:.2f} nm, rows "
                    f"{r['oracle_reg_z_rows_nm']:.2f}, map/floor {r['oracle_map_over_floor']:.3f}",
                    flush=True,
                )
            for stage, seconds in r["timings"].items():
                print(f"{'':>13}{stage}: {seconds:.1f} s", flush=True)
    # the sizes run before 400 patches' learn their ratio now (JSON has no NaN: null without it)
    ref = _reference(rows)
    for r in rows:
        r["time_ratio_400"] = r["wall_s"] / ref["wall_s"] if ref else None
    if ref and any(r["patches"] < 400 for r in rows):
        said = ", ".join(
            f"{r['patches']} x {r['pixels']}²: "
            f"{r['time_ratio_400']:.2f} ({r['patch_ratio_400']:.2f})"
            for r in rows
        )
        print(f"time against 400 patches' (linear: the ratio of patches): {said}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"sizes": rows}, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
