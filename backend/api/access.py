"""The route table: the one place that says what every route needs, and the gatekeeper that
holds every request to it before its body is read.

Each route (method and path) declares its scope, whether the operator lock governs it, whether
it is a safety action the lock never blocks, and whether it is audited. The app refuses to
start with a route missing here, and the role-by-route test is generated from this table.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.routing import Match

from backend.security import audit
from backend.security import scopes as sc
from backend.security.authority import ANONYMOUS, Principal
from backend.security.lock import Locked
from backend.security.tokens import same, sign
from backend.services import Services

log = logging.getLogger("mosaic_afm.server")

#: Methods that may change something.
CHANGES = frozenset({"POST", "PUT", "PATCH", "DELETE"})
#: The browser session's cookies: the access token (HttpOnly), the refresh token (HttpOnly,
#: sent to ``/api/auth`` only) and the CSRF token the page's script echoes in a header.
ACCESS_COOKIE = "mosaic_access"
REFRESH_COOKIE = "mosaic_refresh"
CSRF_COOKIE = "mosaic_csrf"
CSRF_HEADER = "x-csrf-token"


@dataclass(frozen=True)
class Access:
    """What a route needs. ``scope`` None: anyone (logging in)."""

    scope: str | None
    #: refused (423) while another operator holds the lock
    lock: bool = False
    #: a safety action: allowed whoever holds the lock, and logged when not the holder
    safety: bool = False
    #: whether every call is written to the audit trail
    audit: bool = False
    #: whether an anonymous reader (single mode, or MOSAIC_ANONYMOUS_READ) may call it
    anonymous: bool = True


def _read() -> Access:
    return Access(sc.READ)


def _change(scope: str, *, lock: bool = False, safety: bool = False) -> Access:
    return Access(scope, lock=lock, safety=safety, audit=True)


#: Every route of the API, by method and path.
ROUTES: dict[tuple[str, str], Access] = {
    # runs and their patches
    ("POST", "/api/runs/preview"): _read(),  # plans, moves nothing
    ("POST", "/api/runs"): _change(sc.RUNS, lock=True),
    ("GET", "/api/runs"): _read(),
    ("GET", "/api/runs/{run_id}"): _read(),
    ("POST", "/api/runs/{run_id}/start"): _change(sc.RUNS, lock=True),
    ("POST", "/api/runs/{run_id}/pause"): _change(sc.RUNS, lock=True),
    ("POST", "/api/runs/{run_id}/resume"): _change(sc.RUNS, lock=True),
    ("POST", "/api/runs/{run_id}/abort"): _change(sc.RUNS, lock=True, safety=True),
    ("POST", "/api/runs/{run_id}/reset"): _change(sc.RUNS, lock=True),
    ("GET", "/api/runs/{run_id}/patches"): _read(),
    ("GET", "/api/runs/{run_id}/patches/{index}/data"): _read(),
    ("GET", "/api/runs/{run_id}/patches/{index}/preview.png"): _read(),
    ("GET", "/api/runs/{run_id}/live/mosaic.npy"): _read(),
    ("GET", "/api/runs/{run_id}/live/mosaic.json"): _read(),
    ("POST", "/api/runs/{run_id}/patches/{index}/rescan"): _change(sc.RUNS, lock=True),
    ("POST", "/api/runs/offline"): _change(sc.RUNS),  # data only: the instrument is not used
    # merges
    ("POST", "/api/runs/{run_id}/merges"): _change(sc.MERGES),
    ("GET", "/api/runs/{run_id}/merges"): _read(),
    ("GET", "/api/merges/{job_id}"): _read(),
    ("POST", "/api/merges/{job_id}/cancel"): _change(sc.MERGES),
    ("GET", "/api/merges/{job_id}/mosaic.npy"): _read(),
    ("GET", "/api/merges/{job_id}/mosaic.json"): _read(),
    ("GET", "/api/merges/{job_id}/preview.png"): _read(),
    ("GET", "/api/merges/{job_id}/mosaic.{fmt}"): _read(),
    ("POST", "/api/merges/{job_id}/sem-registration"): _change(sc.MERGES),
    ("GET", "/api/merges/{job_id}/sem-registration"): _read(),
    ("GET", "/api/merges/{job_id}/sem-registrations"): _read(),
    ("GET", "/api/merges/{job_id}/sem-overlay.png"): _read(),
    ("GET", "/api/merges/{job_id}/sem-overlay"): _read(),
    ("POST", "/api/merges/{job_id}/sem-registration/apply"): _change(sc.MERGES),
    ("GET", "/api/merges/{job_id}/mosaic-sem.{fmt}"): _read(),
    ("GET", "/api/merges/{job_id}/sem-profile"): _read(),
    # the instrument
    ("GET", "/api/instrument"): _read(),
    ("GET", "/api/instrument/sim/surface"): _read(),
    ("GET", "/api/instrument/sim/sem"): _read(),
    ("POST", "/api/instrument/sim/fault"): _change(sc.FAULTS, lock=True),
    ("POST", "/api/instrument/viewer/session"): Access(sc.READ, anonymous=False),
    ("GET", "/api/instrument/viewer"): _read(),
    # the SEM
    ("POST", "/api/sem/acquire"): _change(sc.SEM, lock=True),
    ("POST", "/api/sem/calibrate"): _change(sc.SEM, lock=True),
    ("GET", "/api/sem/calibration"): _read(),
    ("GET", "/api/sem/microscope"): _read(),
    ("GET", "/api/sem/calibrations"): _read(),
    ("POST", "/api/sem/upload"): _change(sc.SEM),
    ("GET", "/api/sem"): _read(),
    ("GET", "/api/sem/{sem_id}"): _read(),
    ("GET", "/api/sem/{sem_id}/image.png"): _read(),
    ("GET", "/api/sem/{sem_id}/image.npy"): _read(),
    # events
    ("GET", "/api/events"): _read(),
    ("GET", "/api/events/latest"): _read(),
    # logins, keys, the lock, the audit trail, users
    ("POST", "/api/auth/login"): Access(None, audit=True),
    ("POST", "/api/auth/refresh"): Access(None, audit=True),
    ("POST", "/api/auth/logout"): Access(sc.READ, audit=True, anonymous=False),
    ("GET", "/api/auth/whoami"): Access(None),
    ("GET", "/api/auth/sessions"): Access(sc.KEYS, anonymous=False),
    ("DELETE", "/api/auth/sessions/{session_id}"): _change(sc.KEYS),
    ("POST", "/api/keys"): _change(sc.KEYS),
    ("GET", "/api/keys"): Access(sc.KEYS, anonymous=False),
    ("DELETE", "/api/keys/{key_id}"): _change(sc.KEYS),
    ("GET", "/api/lock"): _read(),
    ("POST", "/api/lock"): _change(sc.INSTRUMENT),
    ("DELETE", "/api/lock"): _change(sc.INSTRUMENT),
    ("GET", "/api/audit"): Access(sc.AUDIT, anonymous=False),
    ("GET", "/api/users"): Access(sc.USERS, anonymous=False),
    ("POST", "/api/users"): _change(sc.USERS),
    ("DELETE", "/api/users/{name}"): _change(sc.USERS),
}


def csrf_token(secret: bytes, session_id: int) -> str:
    """The CSRF token of a login session (its page echoes it in ``X-CSRF-Token``)."""
    return sign(secret, f"csrf.{session_id}")


@dataclass(frozen=True)
class Entry:
    route: APIRoute
    method: str
    access: Access


class RouteTable:
    """The API's routes with what each needs; ValueError when a route is not in :data:`ROUTES`
    (or the table names a route the API does not have)."""

    def __init__(self, routes: Iterable[APIRoute], table: dict[tuple[str, str], Access]) -> None:
        self.entries: list[Entry] = []
        seen: set[tuple[str, str]] = set()
        for route in routes:
            for method in sorted(route.methods or ()):
                key = (method, route.path)
                if key not in table:
                    raise ValueError(
                        f"{method} {route.path} is not in the route table "
                        "(backend/api/access.py ROUTES): say which scope it needs"
                    )
                seen.add(key)
                self.entries.append(Entry(route, method, table[key]))
        extra = set(table) - seen
        if extra:
            raise ValueError(f"the route table names routes the API lacks: {sorted(extra)}")

    def match(self, request: Request) -> tuple[Entry, dict[str, Any]] | None:
        """The entry of the route a request asks for, with its path parameters."""
        for entry in self.entries:
            if entry.method != request.method:
                continue
            found, child = entry.route.matches(request.scope)
            if found == Match.FULL:
                return entry, child.get("path_params", {})
        return None


def unauthorised(users_mode: bool) -> str:
    if users_mode:
        return (
            "log in first: POST /api/auth/login (or the login page), then send the access "
            "token as 'Authorization: Bearer <token>'; scripts send an API key the same way"
        )
    return (
        "this changes the instrument or its data: send 'Authorization: Bearer <token>' with the "
        "server's API token (MOSAIC_API_TOKEN, or the file api_token in the data dir)"
    )


class Gatekeeper:
    """Who a request comes from and whether it may go on; and its audit row once answered."""

    def __init__(self, table: RouteTable, services: Callable[[], Services | None]) -> None:
        self.table = table
        self.services = services

    def admit(self, request: Request) -> JSONResponse | None:
        """None to let the request through (its principal put on ``request.state``), else the
        answer that refuses it."""
        services = self.services()
        matched = self.table.match(request)
        if matched is None or services is None:
            return None  # the pages, the API's docs, or a 404; no request before the services
        entry, params = matched
        request.state.entry = entry
        request.state.params = params
        access = entry.access
        authority = services.authority
        who = authority.authenticate(
            request.headers.get("authorization"),
            request.cookies.get(ACCESS_COOKIE),
            request.headers.get("x-operator"),
        )
        if who is not None:
            request.state.principal = who
        if access.scope is None:
            return None
        if who is None:
            anonymous_read = services.settings.anonymous_read or not authority.users_mode
            if not (anonymous_read and access.anonymous and access.scope == sc.READ):
                return JSONResponse(
                    {"detail": unauthorised(authority.users_mode)},
                    401,
                    headers={"WWW-Authenticate": "Bearer"},
                )
            who = ANONYMOUS
            request.state.principal = who
        if access.scope not in who.scopes:
            by = ", by an API key" if who.via == "key" else ""
            return JSONResponse(
                {
                    "detail": f"{who.name} ({who.role}{by}) may not do this: it needs the "
                    f"scope '{access.scope}'"
                },
                403,
            )
        if who.cookie and request.method in CHANGES and who.session_id is not None:
            given = request.headers.get(CSRF_HEADER, "")
            if not same(given, csrf_token(authority.secret, who.session_id)):
                return JSONResponse(
                    {"detail": "a change from the browser session needs its X-CSRF-Token header"},
                    403,
                )
        if access.lock:
            holder = services.lock.other(who)
            if holder is not None:
                if not access.safety:
                    return JSONResponse({"detail": str(Locked(holder))}, 423)
                request.state.audit_note = f"not the lock's holder ({holder.name})"
                log.warning(
                    "%s asked for %s while %s holds the lock",
                    who.name,
                    request.url.path,
                    holder.name,
                )
        return None

    def audited(self, request: Request) -> bool:
        entry: Entry | None = getattr(request.state, "entry", None)
        return entry is not None and entry.access.audit

    async def record(self, request: Request, status: int, body: bytes) -> None:
        """Write the audit row of an answered (or refused) audited request."""
        services = self.services()
        if services is None or not self.audited(request):
            return
        entry: Entry = request.state.entry
        params: dict[str, Any] = getattr(request.state, "params", {})
        who: Principal | None = getattr(request.state, "principal", None)
        user = getattr(request.state, "audit_user", None) or (who.name if who else "anonymous")
        detail: dict[str, Any] = {}
        answer = _json(body)
        if status >= 400 and isinstance(answer, dict) and "detail" in answer:
            detail["error"] = str(answer["detail"])[:300]
        for key in ("audit_note", "audit_reason"):
            value = getattr(request.state, key, None)
            if value:
                detail[key.removeprefix("audit_")] = value
        if who is not None and who.via == "key":
            detail["key"] = who.key_id
        run_id = params.get("run_id")
        creates_run = entry.route.path in ("/api/runs", "/api/runs/offline")
        if run_id is None and creates_run and status == 201 and isinstance(answer, dict):
            run_id = answer.get("id")
        client = request.client.host if request.client else ""
        await asyncio.to_thread(
            audit.record,
            services.sessions,
            user=user,
            address=client,
            action=entry.route.name,
            target=f"{request.method} {request.url.path}",
            run_id=_run_id(run_id),
            status=status,
            detail=detail,
        )


def _run_id(value: Any) -> int | None:
    """A run's id from a path parameter or an answer (a string of digits or an int)."""
    text = str(value)
    return int(text) if text.isdigit() and len(text) < 16 else None


def _json(body: bytes) -> Any:
    if not body or len(body) > 100_000:
        return None
    try:
        return json.loads(body)
    except ValueError:
        return None
