"""``mosaic-afm merge MANIFEST --out DIR``: merge a patch set into one mosaic."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from backend.cli.common import ProgressBar, UsageError, float_pair
from backend.cli.formats_cmd import add_scan_options, read_scan_args

if TYPE_CHECKING:
    import merge

#: The exit code of a merge written but not to be trusted (its verdict says why).
UNTRUSTED = 3


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "merge",
        help="merge a patch set (manifest.json) or a folder of AFM files into one mosaic",
        description="Fuse all patches of a patch set simultaneously (GPA-ICP) into one "
        "topography. SOURCE is a manifest.json (or its folder), or AFM files and folders of "
        "them (read and placed as `import` does, in one step). The last line is the verdict; "
        "the exit code is 3 when the mosaic is written but not to be trusted (no overlaps, "
        "patches that overlap nothing, most places unconfirmed).",
    )
    p.add_argument(
        "sources",
        nargs="+",
        metavar="SOURCE",
        help="manifest.json or its folder; or AFM files, or folders of them",
    )
    p.add_argument("--out", required=True, help="folder for mosaic.npy, mosaic.json, preview.png")
    p.add_argument(
        "--method",
        default="default",
        choices=["default", "paper", "nominal", "zlevel"],
        help="default: robust start + full-resolution point-to-plane GPA; paper: the published "
        "GPA-ICP; nominal: no correction; zlevel: Z offsets only",
    )
    p.add_argument(
        "--cell", type=float, help="down-sampling cell, metres (default: raster spacing)"
    )
    p.add_argument("--max-iter", type=int, help="iteration cap")
    p.add_argument("--max-shift", type=float, help="largest stage error searched, metres")
    p.add_argument(
        "--coarse-cell",
        type=float,
        help="cell of the coarse start's correlation, metres (default: ~32 cells per patch side; "
        "finer keeps fine texture, e.g. a grating's flat faces at a few nm per pixel)",
    )
    p.add_argument("--pixel", type=float_pair, help="mosaic pixel size dx[,dy], metres")
    p.add_argument(
        "--self-calibrate",
        action="store_true",
        help="measure the scanner's row and column bend shared by every patch (open-loop piezo "
        "hysteresis and creep) from the overlaps and take it out, then merge again",
    )
    add_scan_options(p)
    p.add_argument("--no-preview", action="store_true", help="do not write preview.png")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import merge
    from backend.allocator import share_one_heap, stage_trimmer

    share_one_heap()  # before the merge's threads start
    start = time.perf_counter()
    try:
        config = merge.MergeConfig(
            method=args.method,
            cell=args.cell,
            max_iter=args.max_iter,
            max_shift=args.max_shift,
            coarse_cell=args.coarse_cell,
            pixel_size=args.pixel,
            self_calibrate=args.self_calibrate,
        )
        patch_set = _patch_set(args)
    except (merge.PatchSetError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    bar = None if args.quiet else ProgressBar()
    try:
        result = merge.run(
            patch_set,
            config,
            progress=bar,
            status=stage_trimmer(None if bar is None else bar.status),
        )
    finally:
        if bar is not None:
            bar.close()
    try:
        merge.write_result(result, args.out, patch_set=patch_set, preview=not args.no_preview)
    except OSError as exc:
        raise UsageError(f"cannot write to {args.out}: {exc}") from None
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if result.distortion is not None and any(result.distortion.significant):
        bx, by = result.distortion.peak_to_valley
        print(f"scanner bend taken out: {bx * 1e9:.2f} nm along x, {by * 1e9:.2f} nm along y")
    elif result.distortion is not None:
        print("scanner bend: none stood out of the noise; the patches were merged as scanned")
    ny, nx = result.mosaic.heights.shape
    rms = [r.residual_rms for r in result.patches if r.correspondences]
    residual = f"{np.median(rms) * 1e9:.2f} nm" if rms else "n/a"
    elapsed = time.perf_counter() - start
    print(
        f"merged {len(patch_set)} patches ({result.method}) in {elapsed:.1f} s: "
        f"{result.iterations} iterations, {'converged' if result.converged else 'not converged'}, "
        f"median patch residual {residual}, mosaic {nx} x {ny} px -> {args.out}"
    )
    from merge.report.verdict import verdict

    said = verdict(result)
    print(said.line)
    return 0 if said.trusted else UNTRUSTED


def _patch_set(args: argparse.Namespace) -> merge.PatchSet:
    """The patch set of a manifest (or its folder), else of scan files and folders."""
    import merge

    sources = [Path(s) for s in args.sources]
    first = sources[0]
    if len(sources) == 1 and (first.suffix == ".json" or (first / "manifest.json").is_file()):
        return merge.read_patch_set(first)
    return read_scan_args(args.sources, args)
