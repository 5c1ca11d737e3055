"""What every HTTP request meets before a route sees it: the host it names, the token a change
needs, the size of its body (whatever its encoding) and the security headers of the answer.

Plain ASGI, no per-request task or stream wrapping: a status poll stays cheap, and nothing
here waits on anything but the request's own bytes.
"""

from __future__ import annotations

import ipaddress
import json
import logging
from typing import Protocol

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("mosaic_afm.server")

#: Routes that take files (multipart); every other body is JSON and small.
UPLOADS = frozenset({"/api/sem/upload", "/api/runs/offline"})


def content_security_policy(viewer_port: int | None) -> str:
    """The pages' own scripts, styles and images only; the 3D viewer (its own port on the
    page's host) in a frame; the pages themselves in nobody's frame."""
    frames = "'self'" if viewer_port is None else f"'self' *:{viewer_port}"
    return (
        "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; "
        f"script-src 'self'; connect-src 'self'; frame-src {frames}; "
        "frame-ancestors 'none'; base-uri 'none'; form-action 'self'; object-src 'none'"
    )


def loopback_names(host: str) -> list[str]:
    """The Host header values a server bound to ``host`` answers by default: its own name
    and, bound to loopback, the loopback names (a page elsewhere cannot rebind a name to it).
    An empty list (bound to every interface): no check unless hosts are configured."""
    if host in ("0.0.0.0", "::", ""):
        return []
    names = {host, "localhost", "127.0.0.1", "::1", "[::1]"}
    try:
        if not ipaddress.ip_address(host).is_loopback:
            names = {host}
    except ValueError:  # a name, not an address
        if host != "localhost":
            names = {host}
    return sorted(names)


def _host_of(header: str) -> str:
    """The host part of a Host header: ``name:port`` -> name, ``[::1]:8000`` -> ``[::1]``."""
    if header.startswith("["):
        return header[: header.find("]") + 1] if "]" in header else header
    return header.rsplit(":", 1)[0] if header.count(":") == 1 else header


class BodyTooLarge(HTTPException):
    """A body past its limit, whatever announced (or did not announce) its length."""

    def __init__(self, limit: int) -> None:
        super().__init__(413, f"the body is larger than the {limit} byte limit for this route")


def counted(receive: Receive, limit: int) -> Receive:
    """``receive`` that raises :class:`BodyTooLarge` once more than ``limit`` bytes came:
    a chunked body is cut off as soon as it passes, never read in full."""
    total = 0

    async def inner() -> Message:
        nonlocal total
        message = await receive()
        if message["type"] == "http.request":
            total += len(message.get("body", b""))
            if total > limit:
                raise BodyTooLarge(limit)
        return message

    return inner


class Keeper(Protocol):
    """Who a request comes from and whether it may go on (:mod:`backend.api.access`)."""

    def admit(self, request: Request) -> JSONResponse | None:
        """None to let ``request`` through, else the answer that refuses it."""

    def audited(self, request: Request) -> bool:
        """Whether ``request``'s answer is written to the audit trail."""

    async def record(self, request: Request, status: int, body: bytes) -> None:
        """Write the audit row of ``request`` answered with ``status`` and ``body``."""


class Gate:
    """The checks above, as ASGI middleware around the whole app.

    ``keeper`` says who a request comes from and refuses what they may not do, before the
    body is read, and writes the audit row of a change before its answer leaves (a client
    that sees the answer finds the row); ``hosts`` are the Host names answered (empty: any);
    ``limits`` are the body limits (bytes) of uploads and of every other route."""

    def __init__(
        self,
        inner: ASGIApp,
        *,
        keeper: Keeper,
        hosts: list[str],
        upload_limit: int,
        json_limit: int,
        policy: str,
    ) -> None:
        self.inner = inner
        self.keeper = keeper
        self.hosts = frozenset(h.lower() for h in hosts)
        self.upload_limit = upload_limit
        self.json_limit = json_limit
        self.headers = [
            (b"content-security-policy", policy.encode()),
            (b"x-frame-options", b"DENY"),
            (b"x-content-type-options", b"nosniff"),
            (b"referrer-policy", b"same-origin"),
        ]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.inner(scope, receive, send)
            return
        request = Request(scope)
        refused = self._refusal(request)
        if refused is not None:
            await self.keeper.record(request, refused.status_code, bytes(refused.body))
            await refused(scope, receive, send)
            return
        limit = self._limit(scope["path"])
        started = False
        held: Message | None = None  # an audited answer's start, until its first body part
        audited = self.keeper.audited(request)

        async def secured(message: Message) -> None:
            nonlocal started, held
            if message["type"] == "http.response.start":
                started = True
                message = {**message, "headers": [*message.get("headers", []), *self.headers]}
                if audited:
                    held = message
                    return
            elif message["type"] == "http.response.body" and held is not None:
                start, held = held, None
                await self.keeper.record(request, start["status"], message.get("body", b""))
                await send(start)
            await send(message)

        try:
            await self.inner(scope, counted(receive, limit), secured)
        except BodyTooLarge as exc:  # raised where no handler turned it into an answer
            if started:
                raise
            await JSONResponse({"detail": exc.detail}, 413)(scope, receive, secured)

    def _limit(self, path: str) -> int:
        """The body limit of the route at ``path``, bytes."""
        return self.upload_limit if path in UPLOADS else self.json_limit

    def _refusal(self, request: Request) -> JSONResponse | None:
        """What a request is refused with before its body is read."""
        if self.hosts:
            host = _host_of(request.headers.get("host", "")).lower()
            if host not in self.hosts:
                log.warning("refused a request for host %r", host[:100])
                return JSONResponse(
                    {"detail": "this server does not answer for that Host name (MOSAIC_HOSTS)"},
                    400,
                )
        refused = self.keeper.admit(request)
        if refused is not None:
            return refused
        length = request.headers.get("content-length")
        if length is not None:
            if not length.isdigit():
                return JSONResponse({"detail": "Content-Length must be a number"}, 400)
            limit = self._limit(request.url.path)
            if int(length) > limit:
                return JSONResponse({"detail": BodyTooLarge(limit).detail}, 413)
        return None


def safe_errors(errors: list[dict[str, object]]) -> list[dict[str, object]]:
    """Validation errors as an answer can carry them: location, message and type, with the
    offending input only where it is short and plain JSON (never a 50 MB body echoed back,
    never a NaN that JSON cannot write)."""
    out: list[dict[str, object]] = []
    for error in errors[:50]:
        loc = error.get("loc", ())
        item: dict[str, object] = {
            "loc": list(loc)[:10] if isinstance(loc, list | tuple) else [],
            "msg": str(error.get("msg", ""))[:500],
            "type": str(error.get("type", "")),
        }
        value = error.get("input")
        try:
            text = json.dumps(value, allow_nan=False)
        except (TypeError, ValueError):
            text = None
        if text is not None and len(text) <= 200:
            item["input"] = value
        out.append(item)
    return out
