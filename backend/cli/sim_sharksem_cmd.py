"""``mosaic-afm sim-sharksem``: the simulated TESCAN SEM on its SharkSEM ports."""

from __future__ import annotations

import argparse
import math
from typing import Any

from backend.cli.common import UsageError
from backend.cli.sim_cmd import serve_until_interrupted


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "sim-sharksem",
        help="serve a simulated TESCAN SEM over SharkSEM (control port, data port + 1)",
        description="Speak TESCAN's SharkSEM remote-control protocol on TCP: requests on PORT, "
        "images on PORT + 1 (port 0 picks a free pair and prints it). The SEM looks at the "
        "same default sample as sim://, its scan rotated and scaled against the sample stage.",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=0, help="control port (0 picks a free one)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample and the noise")
    p.add_argument("--surface", default="folded", help="folded (default) or chessboard")
    p.add_argument(
        "--sem-rotation", type=float, default=3.0, help="scan rotation against the stage, deg"
    )
    p.add_argument("--sem-scale", type=float, default=1.025, help="scale against the stage")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hardware.microscope import SIM_SAMPLE_SIZE
    from hardware.sim.sem import SEMGeometry, SimulatedSEM
    from hardware.sim.sharksem_server import SharkSEMServer
    from hardware.sim.surfaces import surface_by_name

    if not 0 <= args.port <= 65534:
        raise UsageError(f"--port must be in 0..65534 (data on port + 1), got {args.port}")
    if not (math.isfinite(args.sem_rotation) and math.isfinite(args.sem_scale)):
        raise UsageError("--sem-rotation and --sem-scale must be finite numbers")
    if not 0.5 <= args.sem_scale <= 2.0:
        raise UsageError(f"--sem-scale must be in 0.5..2, got {args.sem_scale}")
    try:
        surface = surface_by_name(args.surface, seed=args.seed, centred=True, size=SIM_SAMPLE_SIZE)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    geometry = SEMGeometry(rotation=args.sem_rotation, scale=args.sem_scale)
    try:
        server = SharkSEMServer(
            SimulatedSEM(surface, seed=args.seed, geometry=geometry),
            host=args.host,
            port=args.port,
        )
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.host}:{args.port} and +1: {exc}") from None
    port = server.address[1]
    print(f"SharkSEM simulator at {server.url} (control {port}, data {port + 1})", flush=True)
    return serve_until_interrupted(server)
