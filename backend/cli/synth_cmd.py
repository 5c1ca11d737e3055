"""``mosaic-afm synth --out DIR``: a synthetic patch set with its true corrections beside it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from backend.cli.common import UsageError, float_pair, int_pair


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "synth",
        help="write a synthetic patch set with known drift (for tests and demos)",
        description="Cut a sample surface into overlapping, drifting, noisy patches in snake "
        "order; write manifest.json, one .npy per patch, truth.json (true transforms) and "
        "truth.npy (the true surface).",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--surface",
        default="chessboard",
        choices=["chessboard", "folded", "image"],
        help="TGX1-like chessboard, folded organic surface, or a height image (--image)",
    )
    p.add_argument("--image", help="2-D .npy height image in metres (rows along y)")
    p.add_argument("--image-pixel", type=float_pair, help="pixel size of --image dx[,dy], metres")
    p.add_argument("--rows", type=int, default=5)
    p.add_argument("--cols", type=int, default=10)
    p.add_argument(
        "--patch",
        type=float_pair,
        default=(0.6e-6, 1.2e-6),
        help="patch scan range width,height in metres (default 0.6e-6,1.2e-6)",
    )
    p.add_argument("--pixels", type=int_pair, default=(30, 60), help="pixels per patch nx,ny")
    p.add_argument("--overlap", type=float_pair, default=(0.5, 1 / 3), help="overlap fractions")
    p.add_argument("--start", type=float_pair, default=(0.0, 0.0), help="origin of patch 0, m")
    p.add_argument("--drift", default="typical", choices=["typical", "harsh", "none"])
    p.add_argument("--drift-scale", type=float, default=1.0, help="scale the XY and Z errors")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from backend.synthetic import patch_set_from_synth
    from hardware.sim.drift import DriftModel
    from hardware.sim.surfaces import surface_by_name
    from hardware.sim.synth import synthesize
    from merge import write_patch_set

    if args.rows < 1 or args.cols < 1 or args.rows * args.cols < 2:
        raise UsageError("need at least two patches (--rows x --cols >= 2)")
    if min(args.pixels) < 2:
        raise UsageError("need at least 2 x 2 pixels per patch (--pixels)")
    if min(args.patch) <= 0:
        raise UsageError("--patch sizes must be positive (metres)")
    if not all(0 <= o < 1 for o in args.overlap):
        raise UsageError("--overlap fractions must be in [0, 1)")
    try:
        surface = surface_by_name(
            args.surface, seed=args.seed, image=args.image, pixel=args.image_pixel
        )
    except (OSError, ValueError) as exc:
        raise UsageError(f"cannot make the {args.surface} surface: {exc}") from None
    model = {
        "typical": DriftModel.typical(),
        "harsh": DriftModel.harsh(),
        "none": DriftModel(0, 0, 0, 0, 0, 0, 0),
    }[args.drift].scaled(args.drift_scale)
    synth = synthesize(
        surface,
        rows=args.rows,
        cols=args.cols,
        patch_size=args.patch,
        pixels=args.pixels,
        overlap=args.overlap,
        start=args.start,
        drift=model,
        seed=args.seed,
    )
    if any(not np.isfinite(s.heights).any() for s in synth):
        raise UsageError("some patches fall outside the image: reduce --rows/--cols or --patch")
    out = Path(args.out)
    patch_set = patch_set_from_synth(synth)
    write_patch_set(patch_set, out)
    # the true surface over the nominal area, at the patch pixel pitch
    dx, dy = synth[0].pixel_size
    x0 = min(s.origin[0] for s in synth)
    y0 = min(s.origin[1] for s in synth)
    x1 = max(s.origin[0] + (s.heights.shape[1] - 1) * dx for s in synth)
    y1 = max(s.origin[1] + (s.heights.shape[0] - 1) * dy for s in synth)
    xs = np.arange(x0, x1 + 0.5 * dx, dx)
    ys = np.arange(y0, y1 + 0.5 * dy, dy)
    xx, yy = np.meshgrid(xs, ys)
    np.save(out / "truth.npy", surface.height(xx, yy))
    truth = {
        "format": "mosaic-afm/synth-truth@1",
        "units": "m",
        "surface": args.surface,
        "seed": args.seed,
        "drift": {k: getattr(model, k) for k in model.__dataclass_fields__},
        "truth_surface": {"file": "truth.npy", "origin": [x0, y0], "pixel_size": [dx, dy]},
        "z_drift_model": "z_true = (R p + t)_z - z_drift * (s - 0.5), s = scan-time fraction",
        "patches": [
            {
                "id": s.id,
                "rotation": s.rotation.tolist(),
                "translation": s.translation.tolist(),
                "z_drift": s.z_drift,
            }
            for s in synth
        ],
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    print(
        f"wrote {len(synth)} patches ({args.surface}, drift {args.drift}) to {out}", file=sys.stderr
    )
    return 0
