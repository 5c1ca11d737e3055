"""``mosaic-afm sim-scan --out DIR``: scan a small mosaic on the simulated instrument."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from backend.cli.common import UsageError, float_pair, int_pair


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "sim-scan",
        help="scan a mosaic on the simulated AFM-in-SEM and write a patch set",
        description="Move, land, scan and retract every patch in snake order on the simulated "
        "instrument (through the MCS driver and protocol simulator); write a patch set.",
    )
    p.add_argument("--out", required=True, help="output folder for manifest.json and patches")
    p.add_argument("--surface", default="chessboard", choices=["chessboard", "folded", "image"])
    p.add_argument("--image", help="for --surface image: 2-D .npy of heights in metres")
    p.add_argument("--image-pixel", type=float_pair, help="pixel size of --image dx[,dy], m")
    p.add_argument("--rows", type=int, default=2)
    p.add_argument("--cols", type=int, default=3)
    p.add_argument("--patch", type=float_pair, default=(0.6e-6, 1.2e-6), help="metres w,h")
    p.add_argument("--pixels", type=int_pair, default=(30, 60), help="pixels nx,ny")
    p.add_argument("--overlap", type=float_pair, default=(0.5, 1 / 3))
    p.add_argument("--start", type=float_pair, default=(0.0, 0.0), help="first patch origin, m")
    p.add_argument("--line-rate", type=float, default=2.0, help="scan lines per second")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hardware.sim.instrument import SimulatedAFM
    from hardware.sim.mosaic import scan_mosaic
    from hardware.sim.surfaces import surface_by_name
    from merge import Patch, PatchSet, write_patch_set

    if args.rows < 1 or args.cols < 1:
        raise UsageError("--rows and --cols must be at least 1")
    if min(args.pixels) < 2:
        raise UsageError("--pixels must be at least 2 per axis")
    if not all(0 < s <= 1.6e-6 for s in args.patch):
        raise UsageError("--patch must fit the 1.6 µm fine range (metres, e.g. 0.6e-6,1.2e-6)")
    if not all(0 <= o < 1 for o in args.overlap):
        raise UsageError("--overlap fractions must be in [0, 1)")
    if not args.line_rate > 0:
        raise UsageError("--line-rate must be positive")
    try:
        surface = surface_by_name(
            args.surface, seed=args.seed, image=args.image, pixel=args.image_pixel, centred=True
        )
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot make the {args.surface} surface: {exc}") from None
    wall = time.perf_counter()
    with SimulatedAFM(surface, seed=args.seed) as afm:
        scanned = scan_mosaic(
            afm,
            rows=args.rows,
            cols=args.cols,
            patch_size=args.patch,
            pixels=args.pixels,
            overlap=args.overlap,
            start=args.start,
            line_rate=args.line_rate,
            on_patch=lambda p: print(
                f"patch {p.plan.index + 1} (row {p.plan.row}, col {p.plan.col}) scanned",
                file=sys.stderr,
            ),
        )
        simulated = afm.clock.now()
    patch_set = PatchSet(
        Patch(
            id=f"p{s.plan.index:03d}",
            heights=s.heights,
            origin=s.origin,
            pixel_size=s.pixel_size,
            order=s.plan.index,
            row=s.plan.row,
            col=s.plan.col,
        )
        for s in scanned
    )
    write_patch_set(
        patch_set,
        args.out,
        extra={"source": "mosaic-afm sim-scan", "surface": args.surface, "seed": args.seed},
    )
    print(
        f"scanned {len(scanned)} patches in {time.perf_counter() - wall:.1f} s "
        f"({simulated:.0f} s simulated) -> {args.out}"
    )
    return 0
