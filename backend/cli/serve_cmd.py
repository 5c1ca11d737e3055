"""``mosaic-afm serve``: the acquisition server under uvicorn."""

from __future__ import annotations

import argparse
from typing import Any

from backend.cli.common import UsageError


def add_parser(sub: Any) -> None:
    p = sub.add_parser(
        "serve",
        help="run the acquisition server (REST API, pages, event stream)",
        description="Migrate the database, open the instrument (MOSAIC_INSTRUMENT, default the "
        "simulated one) and serve the API. Settings come from MOSAIC_* variables or .env.",
    )
    p.add_argument("--host", help="interface to listen on (default MOSAIC_HOST, 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default MOSAIC_PORT, 8000)")
    p.add_argument("--data-dir", help="data folder (default MOSAIC_DATA_DIR, ./data)")
    p.add_argument("--instrument", help="instrument URL (default MOSAIC_INSTRUMENT, sim://)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn
    from pydantic import ValidationError

    from backend.api.app import create_app
    from backend.security.authority import NoUsers
    from backend.services import DatabaseDamaged, Services
    from backend.settings import Settings
    from hardware.microscope import ConfigurationError
    from hardware.nanonis.errors import NanonisError
    from hardware.smaract_errors import MCSError

    overrides = {
        k: v
        for k, v in {
            "host": args.host,
            "port": args.port,
            "data_dir": args.data_dir,
            "instrument": args.instrument,
        }.items()
        if v is not None
    }
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()
        )
        raise UsageError(f"bad settings: {problems}") from None
    try:
        services = Services.open(settings)
    except (DatabaseDamaged, NoUsers) as exc:
        raise UsageError(str(exc)) from None
    except (ConfigurationError, MCSError, NanonisError) as exc:
        raise UsageError(f"cannot open the instrument {settings.instrument!r}: {exc}") from None
    except OSError as exc:
        raise UsageError(
            f"cannot use the data directory {settings.data_dir}: {exc.strerror or exc}"
            + (f" ({exc.filename})" if exc.filename else "")
        ) from None
    base = f"http://{settings.host}:{settings.port}"
    viewer = services.viewer
    access = (
        f"users (log in at {base}/login.html; add users: mosaic-afm users add)"
        if settings.auth == "users"
        else f"single user (the API token in {settings.data_dir / 'api_token'})"
    )
    print(
        f"Mosaic AFM on {services.microscope.description}\n"
        f"  pages:     {base}/\n"
        f"  API:       {base}/api/runs\n"
        f"  API docs:  {base}/docs\n"
        f"  events:    {base}/api/events\n"
        f"  access:    {access}\n"
        f"  3D viewer: {viewer.url if viewer is not None else 'off (MOSAIC_VIEWER=false)'}",
        flush=True,
    )
    try:
        uvicorn.run(
            create_app(settings, services=services),
            host=settings.host,
            port=settings.port,
            log_level="info",
        )
    finally:
        services.close()
    return 0
