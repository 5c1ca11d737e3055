"""``mosaic-afm sim-mcs``: run the SmarAct MCS protocol simulator as a TCP server."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from backend.cli.common import UsageError


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "sim-mcs",
        help="serve a simulated SmarAct MCS controller on a TCP port",
        description="Speak the MCS ASCII protocol on TCP, for pyserial URLs socket://HOST:PORT.",
    )
    add_server_options(p, seed="seed of the channel physics")
    p.add_argument("--channels", type=int, default=3, help="number of channels (1-64)")
    p.set_defaults(func=run)


def add_server_options(p: Any, *, seed: str) -> None:
    """``--host``, ``--port``, ``--speed`` and ``--seed``: what every protocol simulator takes."""
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=0, help="port (0 picks a free one)")
    p.add_argument(
        "--speed",
        default="max",
        help="simulated seconds per wall second, or 'max' for as fast as possible",
    )
    p.add_argument("--seed", type=int, default=0, help=seed)


def parse_speed(text: str) -> float | None:
    """``max`` or a positive number of simulated seconds per wall second."""
    if text == "max":
        return None
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"--speed must be 'max' or a positive number, got {text!r}") from None
    if not value > 0:
        raise UsageError(f"--speed must be positive, got {text!r}")
    return value


def run(args: argparse.Namespace) -> int:
    from hardware.sim.clock import SimClock
    from hardware.sim.mcs_device import MCSDevice
    from hardware.sim.mcs_server import MCSServer

    if not 0 <= args.port <= 65535:
        raise UsageError(f"--port must be in 0..65535, got {args.port}")
    try:
        device = MCSDevice(channels=args.channels, seed=args.seed)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        server = MCSServer(
            device, host=args.host, port=args.port, clock=SimClock(parse_speed(args.speed))
        )
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.host}:{args.port}: {exc}") from None
    print(f"MCS simulator with {args.channels} channels at {server.url}", flush=True)
    return serve_until_interrupted(server)


def serve_until_interrupted(server: Any, *also: Any) -> int:
    """Serve until Ctrl-C, then stop ``server`` and close what ``also`` names."""
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    finally:
        server.stop()
        for thing in also:
            thing.close()
    return 0
