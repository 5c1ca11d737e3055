"""Logins and sessions, API keys, the operator lock, the audit trail and users.

What each route needs is in the route table (:mod:`backend.api.access`); these handlers only
do what they are asked, by whoever the gate let through.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated

from fastapi import APIRouter, Body, HTTPException, Query, Request, Response
from sqlalchemy import select

from backend.api.access import ACCESS_COOKIE, CSRF_COOKIE, CSRF_HEADER, REFRESH_COOKIE, csrf_token
from backend.api.account_schemas import (
    AuditOut,
    KeyIn,
    KeyOut,
    LockIn,
    LockOut,
    LoginIn,
    NewKeyOut,
    RefreshIn,
    SessionOut,
    TokensOut,
    UnlockIn,
    UserIn,
    UserOut,
    WhoOut,
)
from backend.api.deps import PrincipalDep, ServicesDep, SessionDep
from backend.db.access_models import User
from backend.security import audit
from backend.security import scopes as sc
from backend.security.authority import Refused, Tokens
from backend.security.lock import Holder, Locked
from backend.security.tokens import refresh_session, same
from backend.services import Services
from backend.viewer_access import COOKIE as VIEWER

router = APIRouter(tags=["access"])

SINGLE = (
    "the server runs in the single-user mode (one API token): users, sessions and keys are "
    "for MOSAIC_AUTH=users"
)


def _refused(exc: Refused) -> HTTPException:
    headers = {"Retry-After": f"{exc.retry_after:.0f}"} if exc.retry_after else None
    return HTTPException(exc.status, exc.detail, headers=headers)


def _users_mode(services: Services) -> None:
    if not services.authority.users_mode:
        raise HTTPException(409, SINGLE)


def _address(request: Request) -> str:
    return request.client.host if request.client else ""


def _cookies(response: Response, services: Services, tokens: Tokens) -> str:
    """Put a session's tokens in the browser's cookies; its CSRF token (also a cookie the
    page's script reads)."""
    secure = services.settings.secure_cookies
    csrf = csrf_token(services.authority.secret, tokens.session_id)
    response.set_cookie(
        ACCESS_COOKIE,
        tokens.access_token,
        max_age=tokens.expires_in,
        httponly=True,
        samesite="strict",
        secure=secure,
    )
    response.set_cookie(
        REFRESH_COOKIE,
        tokens.refresh_token,
        max_age=services.settings.refresh_ttl,
        path="/api/auth",
        httponly=True,
        samesite="strict",
        secure=secure,
    )
    response.set_cookie(
        CSRF_COOKIE, csrf, max_age=services.settings.refresh_ttl, samesite="strict", secure=secure
    )
    return csrf


def _tokens_out(
    tokens: Tokens, response: Response, services: Services, *, cookie: bool
) -> TokensOut:
    if cookie:
        csrf = _cookies(response, services, tokens)
        return TokensOut(
            access_token=None, refresh_token=None, expires_in=tokens.expires_in, csrf_token=csrf
        )
    return TokensOut(
        access_token=tokens.access_token,
        refresh_token=tokens.refresh_token,
        expires_in=tokens.expires_in,
    )


# -- logins ----------------------------------------------------------------------------------


@router.post("/api/auth/login", response_model=TokensOut)
def login(body: LoginIn, request: Request, response: Response, services: ServicesDep) -> TokensOut:
    """Log in: an access token (short-lived) and a refresh token; with ``cookie``, the
    browser's HttpOnly cookies instead. Failed logins of a name or an address are throttled
    (429 with Retry-After)."""
    _users_mode(services)
    request.state.audit_user = body.username[:64]
    try:
        tokens = services.authority.login(body.username, body.password, _address(request))
    except Refused as exc:
        raise _refused(exc) from None
    return _tokens_out(tokens, response, services, cookie=body.cookie)


@router.post("/api/auth/refresh", response_model=TokensOut)
def refresh(
    request: Request,
    response: Response,
    services: ServicesDep,
    body: Annotated[RefreshIn | None, Body()] = None,
) -> TokensOut:
    """New tokens for a session (the refresh token is replaced: the old one is refused from
    now on). The browser sends its refresh cookie and the CSRF header instead of a body."""
    _users_mode(services)
    token = body.refresh_token if body is not None else None
    cookie = token is None
    if cookie:
        token = request.cookies.get(REFRESH_COOKIE, "")
        sid = refresh_session(token)
        given = request.headers.get(CSRF_HEADER, "")
        if sid is None or not same(given, csrf_token(services.authority.secret, sid)):
            raise HTTPException(
                401, "no session to refresh: log in (a browser sends its X-CSRF-Token header)"
            )
    try:
        tokens = services.authority.refresh(token or "")
    except Refused as exc:
        raise _refused(exc) from None
    return _tokens_out(tokens, response, services, cookie=cookie)


@router.post("/api/auth/logout", status_code=204)
def logout(who: PrincipalDep, services: ServicesDep) -> Response:
    """End this session (its access and refresh tokens are refused from now on)."""
    if who.session_id is None:
        raise HTTPException(
            409, "only a login session logs out; a key is revoked with DELETE /api/keys/{id}"
        )
    services.authority.end_session(who.user_id, who.session_id)
    response = Response(status_code=204)
    gone = ((ACCESS_COOKIE, "/"), (REFRESH_COOKIE, "/api/auth"), (CSRF_COOKIE, "/"), (VIEWER, "/"))
    for name, path in gone:
        response.delete_cookie(name, path=path)
    return response


@router.get("/api/auth/whoami", response_model=WhoOut)
def whoami(request: Request, services: ServicesDep) -> WhoOut:
    """Who this request is from (nobody: ``user`` None), and the server's mode."""
    who = getattr(request.state, "principal", None)
    settings = services.settings
    return WhoOut(
        mode=settings.auth,
        user=who.name if who else None,
        role=who.role if who else None,
        scopes=sorted(who.scopes) if who else [],
        via=who.via if who else None,
        anonymous_read=settings.anonymous_read or settings.auth == "single",
    )


@router.get("/api/auth/sessions", response_model=list[SessionOut])
def my_sessions(who: PrincipalDep, services: ServicesDep) -> list[SessionOut]:
    """Your login sessions that have not ended."""
    _users_mode(services)
    return [
        SessionOut(
            id=s.id,
            created_at=s.created_at,
            expires_at=s.expires_at,
            address=s.address,
            current=s.id == who.session_id,
        )
        for s in services.authority.sessions_of(who.user_id)
    ]


@router.delete("/api/auth/sessions/{session_id}", status_code=204)
def end_session(session_id: int, who: PrincipalDep, services: ServicesDep) -> Response:
    """End one of your sessions (another browser's, a lost laptop's)."""
    _users_mode(services)
    if not services.authority.end_session(who.user_id, session_id):
        raise HTTPException(404, f"you have no open session {session_id}")
    return Response(status_code=204)


# -- keys ------------------------------------------------------------------------------------


@router.post("/api/keys", status_code=201, response_model=NewKeyOut)
def create_key(body: KeyIn, who: PrincipalDep, services: ServicesDep) -> NewKeyOut:
    """A key for your scripts: it acts for you with at most the scopes given (a subset of
    yours), until it expires or is revoked. The key is in this answer only."""
    _users_mode(services)
    try:
        row, key = services.authority.create_key(
            who, body.scopes, body.expires_in, body.note.strip()
        )
    except Refused as exc:
        raise _refused(exc) from None
    return NewKeyOut(
        id=row.id, key=key, prefix=row.prefix, scopes=row.scopes, expires_at=row.expires_at
    )


@router.get("/api/keys", response_model=list[KeyOut])
def list_keys(who: PrincipalDep, services: ServicesDep) -> list[KeyOut]:
    """Your keys (their prefixes: a key itself is never shown again)."""
    _users_mode(services)
    return [
        KeyOut(
            id=k.id,
            prefix=k.prefix,
            scopes=k.scopes,
            note=k.note,
            created_at=k.created_at,
            expires_at=k.expires_at,
            revoked=k.revoked_at is not None,
        )
        for k in services.authority.keys_of(who.user_id)
    ]


@router.delete("/api/keys/{key_id}", status_code=204)
def revoke_key(key_id: int, who: PrincipalDep, services: ServicesDep) -> Response:
    """Revoke a key: refused from its next request on."""
    _users_mode(services)
    if not services.authority.revoke_key(who, key_id):
        raise HTTPException(404, f"you have no key {key_id} in force")
    return Response(status_code=204)


# -- the operator lock -----------------------------------------------------------------------


def _lock_out(holder: Holder | None, who_id: int) -> LockOut:
    if holder is None:
        return LockOut(held=False, holder=None, note=None, since=None, yours=False)
    return LockOut(
        held=True,
        holder=holder.name,
        note=holder.note,
        since=holder.since,
        yours=holder.user_id == who_id,
    )


@router.get("/api/lock", response_model=LockOut)
def read_lock(who: PrincipalDep, services: ServicesDep) -> LockOut:
    """Who holds the instrument, since when and why."""
    return _lock_out(services.lock.holder, who.user_id)


@router.post("/api/lock", response_model=LockOut)
def take_lock(body: LockIn, who: PrincipalDep, services: ServicesDep) -> LockOut:
    """Hold the instrument (or change your note): others may watch, not change it (423)."""
    try:
        holder = services.lock.take(who, body.note.strip())
    except Locked as exc:
        raise HTTPException(423, str(exc)) from None
    services.events.emit(
        "lock", f"{holder.says()}", data={"holder": holder.name, "note": holder.note}
    )
    return _lock_out(holder, who.user_id)


@router.delete("/api/lock", response_model=LockOut)
def release_lock(
    request: Request,
    who: PrincipalDep,
    services: ServicesDep,
    body: Annotated[UnlockIn | None, Body()] = None,
) -> LockOut:
    """Release your lock; an admin breaks another's with a ``reason`` (logged)."""
    holder = services.lock.holder
    reason = (body.reason if body else "").strip()
    other = holder is not None and holder.user_id != who.user_id
    if other and sc.BREAK_LOCK in who.scopes and not reason:
        raise HTTPException(422, "reason: say why you break another operator's lock")
    try:
        was = services.lock.release(who, force=other and sc.BREAK_LOCK in who.scopes)
    except Locked as exc:
        raise HTTPException(423, str(exc)) from None
    if was is not None:
        if other:
            request.state.audit_reason = f"broke {was.name}'s lock: {reason}"
        said = (
            f"{who.name} broke {was.name}'s lock: {reason}"
            if other
            else f"{who.name} released the lock"
        )
        services.events.emit("lock", said, data={"holder": None, "broken": other})
    return _lock_out(None, who.user_id)


# -- the audit trail -------------------------------------------------------------------------


@router.get("/api/audit", response_model=list[AuditOut])
def read_audit(
    session: SessionDep,
    user: Annotated[str | None, Query(max_length=64)] = None,
    since: Annotated[datetime | None, Query(description="ISO 8601")] = None,
    run: Annotated[int | None, Query(ge=1)] = None,
    action: Annotated[str | None, Query(max_length=64)] = None,
    limit: Annotated[int, Query(ge=1, le=audit.MOST)] = 200,
) -> list[AuditOut]:
    """Every state change asked for, newest first: who, when, from where, what, the outcome."""
    rows = audit.read(session, user=user, since=since, run=run, action=action, limit=limit)
    return [
        AuditOut(
            id=r.id,
            at=r.at,
            user=r.user,
            address=r.address,
            action=r.action,
            target=r.target,
            run_id=r.run_id,
            outcome=r.outcome,
            status=r.status,
            detail=r.detail or {},
        )
        for r in rows
    ]


# -- users -----------------------------------------------------------------------------------


def _user_out(u: User) -> UserOut:
    return UserOut(
        name=u.name, role=u.role, provider=u.provider, disabled=u.disabled, created_at=u.created_at
    )


@router.get("/api/users", response_model=list[UserOut])
def list_users(session: SessionDep) -> list[UserOut]:
    return [_user_out(u) for u in session.scalars(select(User).order_by(User.name))]


@router.post("/api/users", status_code=201, response_model=UserOut)
def add_user(body: UserIn, services: ServicesDep) -> UserOut:
    """Add a user (a local one with a password of 8 characters or more, or one PAM logs in)."""
    try:
        user = services.authority.add_user(
            body.name, body.role, body.password, provider=body.provider
        )
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return _user_out(user)


@router.delete("/api/users/{name}", status_code=204)
def disable_user(name: str, who: PrincipalDep, services: ServicesDep) -> Response:
    """Disable a user: their sessions and keys are refused from now on."""
    if name == who.name:
        raise HTTPException(409, "you cannot disable yourself: ask another admin")
    if not services.authority.set_disabled(name, True):
        raise HTTPException(404, f"no user {name!r}: list them with GET /api/users")
    return Response(status_code=204)
