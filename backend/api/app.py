"""The FastAPI application: factory, lifespan, error handlers, routers."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import OperationalError

from backend.acquisition.control import Conflict, NotFound
from backend.acquisition.planner import PlanError
from backend.acquisition.state import TransitionError
from backend.api import (
    access,
    accounts,
    correlative,
    events,
    instrument,
    merges,
    runs,
    sem,
    uploads,
)
from backend.api.guard import Gate, content_security_policy, loopback_names, safe_errors
from backend.db.space import StorageFull, full_message, is_full
from backend.merge_jobs import JobError
from backend.security.lock import Locked
from backend.services import Services
from backend.settings import Settings
from hardware.errors import ProcedureError
from hardware.microscope import ConfigurationError

log = logging.getLogger("mosaic_afm.server")


#: The API's routers, in the order they are matched.
ROUTERS = (uploads, runs, merges, correlative, instrument, sem, events, accounts)


def api_routes() -> list[APIRoute]:
    """Every route of the API (what the route table must name)."""
    return [r for m in ROUTERS for r in m.router.routes if isinstance(r, APIRoute)]


#: The operator's pages (static files: HTML, CSS, ES modules).
FRONTEND = Path(__file__).resolve().parents[2] / "frontend"


def create_app(settings: Settings | None = None, *, services: Services | None = None) -> FastAPI:
    """The server. ``services`` (already open) is for tests; otherwise the lifespan opens
    them from ``settings``: migrations, instrument, recovery of an earlier stop."""
    cfg = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owned = services is None
        svc = services if services is not None else await asyncio.to_thread(Services.open, cfg)
        svc.events.attach(asyncio.get_running_loop())
        app.state.services = svc
        if svc.token_created and not svc.token_announced and not svc.authority.users_mode:
            svc.token_announced = True
            print(
                f"API token (also in {cfg.data_dir / 'api_token'}): {svc.token}",
                flush=True,
            )
        try:
            yield
        finally:
            if owned:
                await asyncio.to_thread(svc.close)

    app = FastAPI(
        title="Mosaic AFM",
        version="0.1.0",
        summary="Long-range AFM by mosaics: plan, acquire, merge (SI units throughout).",
        lifespan=lifespan,
    )
    if cfg.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=cfg.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=[
                "Authorization",
                "Content-Type",
                "X-Operator",
                "X-CSRF-Token",
                "Last-Event-ID",
            ],
        )

    keeper = access.Gatekeeper(
        access.RouteTable(api_routes(), access.ROUTES),
        lambda: getattr(app.state, "services", None),
    )
    app.add_middleware(
        Gate,
        keeper=keeper,
        hosts=cfg.hosts if cfg.hosts is not None else loopback_names(cfg.host),
        upload_limit=cfg.max_upload_bytes,
        json_limit=cfg.max_json_bytes,
        policy=content_security_policy(cfg.viewer_port if cfg.viewer else None),
    )

    def handler(status: int) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
        async def handle(_: Request, exc: Exception) -> JSONResponse:
            body: dict[str, object] = {"detail": str(exc)}
            if isinstance(exc, PlanError):
                body["field"] = exc.field
            return JSONResponse(body, status)

        return handle

    async def storage_full(_: Request, exc: Exception) -> JSONResponse:
        if isinstance(exc, StorageFull):
            detail = exc.strerror or str(exc)
        elif is_full(exc):
            detail = full_message(cfg.data_dir, then="try again")
        else:  # any other database or file failure: the server's, said plainly
            log.exception("storage failed")
            detail = f"the server could not use its data directory {cfg.data_dir}: see its log"
        return JSONResponse({"detail": detail}, 507 if is_full(exc) else 500)

    async def invalid(_: Request, exc: Exception) -> JSONResponse:
        errors = exc.errors() if isinstance(exc, RequestValidationError) else []
        return JSONResponse({"detail": safe_errors(list(errors))}, 422)

    app.add_exception_handler(RequestValidationError, invalid)
    for storage in (OSError, OperationalError):
        app.add_exception_handler(storage, storage_full)

    for exc_type, status in (
        (PlanError, 422),
        (TransitionError, 409),
        (Conflict, 409),
        (JobError, 409),
        (NotFound, 404),
        (LookupError, 404),
        (ConfigurationError, 409),
        (ProcedureError, 409),
        (Locked, 423),
    ):
        app.add_exception_handler(exc_type, handler(status))

    for module in ROUTERS:
        app.include_router(module.router)
    app.mount("/", StaticFiles(directory=FRONTEND, html=True), name="pages")
    if services is not None:
        app.state.services = services  # usable before (or without) the lifespan, as in tests
    return app
