"""``mosaic-afm sim-nanonis``: a simulated Nanonis controller on TCP, with its MCS stage."""

from __future__ import annotations

import argparse
from typing import Any

from backend.cli.common import UsageError
from backend.cli.sim_cmd import add_server_options, parse_speed, serve_until_interrupted


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "sim-nanonis",
        help="serve a simulated Nanonis controller (and its SmarAct MCS sample stage) on TCP",
        description=(
            "Speak the Nanonis TCP programming interface over the simulated AFM-in-SEM (the "
            "same default sample as sim://): PLL, Z controller, scan, auto-approach, motors. "
            "The sample stage of the same world speaks the MCS protocol on a second port."
        ),
    )
    add_server_options(p, seed="seed of the sample, drift and noise")
    p.add_argument("--stage-port", type=int, default=0, help="MCS stage port (0: a free one)")
    p.add_argument("--surface", default="folded", help="folded (default), chessboard or image")
    p.add_argument(
        "--sem-port",
        type=int,
        default=None,
        help="also serve the world's SEM over SharkSEM on this port (data on port + 1; "
        "0: a free pair), its scan rotated 3 degrees and scaled 1.025 against the stage",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hardware.microscope import ConfigurationError, simulated_afm
    from hardware.sim.nanonis_server import NanonisServer

    for name in ("port", "stage_port"):
        if not 0 <= getattr(args, name) <= 65535:
            raise UsageError(f"--{name.replace('_', '-')} must be in 0..65535")
    if args.sem_port is not None and not 0 <= args.sem_port <= 65534:
        raise UsageError(f"--sem-port must be in 0..65534 (data on port + 1), got {args.sem_port}")
    speed = parse_speed(args.speed)
    config = f"sim://?surface={args.surface}&seed={args.seed}&speed={speed or 'max'}"
    try:
        afm = simulated_afm(config, host=args.host, stage_port=args.stage_port)
    except ConfigurationError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot listen on {args.host}:{args.stage_port}: {exc}") from None
    try:
        server = NanonisServer(afm, host=args.host, port=args.port)
    except OSError as exc:
        afm.close()
        raise UsageError(f"cannot listen on {args.host}:{args.port}: {exc}") from None
    url = server.instrument_url
    also: list[Any] = [afm]
    if args.sem_port is not None:
        sem = _serve_sem(afm, host=args.host, port=args.sem_port, seed=args.seed)
        if sem is None:
            server.stop()
            afm.close()
            raise UsageError(f"cannot listen on {args.host}:{args.sem_port} and the port after")
        also.insert(0, sem)
        url += f"&sem={sem.url}"
        print(f"its SEM (TESCAN SharkSEM) at {sem.url}", flush=True)
    host, port = server.address
    print(f"Nanonis simulator at {host}:{port}", flush=True)
    print(f"its sample stage (SmarAct MCS) at {server.stage_url}", flush=True)
    print(f"MOSAIC_INSTRUMENT={url}", flush=True)
    return serve_until_interrupted(server, *also)


def _serve_sem(afm: Any, *, host: str, port: int, seed: int) -> Any:
    """The SEM of ``afm``'s world on SharkSEM (it sees the stage's moves), or None when the
    ports are taken."""
    from hardware.sim.sem import SimulatedSEM
    from hardware.sim.sharksem_server import SharkSEMServer

    try:
        server = SharkSEMServer(
            SimulatedSEM(
                afm.surface,
                seed=seed,
                stage=afm.stage_position,
                sensor_scale=afm.stage_sensor_scale,
            ),
            host=host,
            port=port,
        )
    except OSError:
        return None
    return server.start()
