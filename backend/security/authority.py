"""Who a request comes from: the single-user mode's one token, or (users mode) a login
session's access token, a browser's session cookie or a script's API key. Also logins,
refreshes, logouts, keys and users, each kept in the database.

A request's identity is looked up once and remembered for a few seconds (a status poll stays
cheap); anything this server revokes (a key, a session, a user) is forgotten at once, so a
revoked key is refused at its next request. A change made by another process (the ``users``
command) takes effect within :data:`REMEMBER` seconds.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from backend.db.access_models import ApiKey, LoginSession, User
from backend.security import scopes as sc
from backend.security.pam import PamUnavailable, pam_login
from backend.security.passwords import hash_password, verify_password
from backend.security.throttle import Throttle
from backend.security.tokens import (
    digest,
    key_prefix,
    load_or_create_secret,
    make_access,
    make_key,
    make_refresh,
    read_access,
    refresh_session,
    same,
)
from backend.settings import Settings

log = logging.getLogger("mosaic_afm.server")

#: Seconds an identity looked up is remembered.
REMEMBER = 5.0
#: A user's name: letters, digits and ``._-``, up to 64 characters.
NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")


@dataclass(frozen=True)
class Principal:
    """Who a request comes from. ``user_id`` 0 is the single-user mode's one identity."""

    name: str
    role: str
    scopes: frozenset[str]
    user_id: int
    #: ``token`` (single mode), ``session`` (access token), ``key`` or ``anonymous``
    via: str
    session_id: int | None = None
    key_id: int | None = None
    #: carried by the browser's session cookie (a change then needs the CSRF header)
    cookie: bool = False

    @property
    def anonymous(self) -> bool:
        return self.via == "anonymous"


ANONYMOUS = Principal("anonymous", "observer", frozenset({sc.READ}), -1, "anonymous")


class NoUsers(RuntimeError):
    """The users mode, with nobody who can log in."""


class Refused(Exception):
    """A login, refresh or key request refused: ``status`` and a ``detail`` that says why."""

    def __init__(self, status: int, detail: str, *, retry_after: float | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.retry_after = retry_after


@dataclass
class Tokens:
    access_token: str
    refresh_token: str
    expires_in: int
    session_id: int


def check_name(name: str) -> str:
    """A user's name as stored; ValueError for one that cannot be."""
    name = name.strip()
    if not name or len(name) > 64 or not set(name) <= NAME_CHARS:
        raise ValueError(
            f"a user's name is 1-64 letters, digits, '.', '_' or '-' (got {name[:70]!r})"
        )
    return name


def _now() -> datetime:
    return datetime.now(UTC)


@dataclass
class Authority:
    settings: Settings
    sessions: sessionmaker[Session]
    #: the single-user mode's token
    token: str
    secret: bytes = b""
    throttle: Throttle = field(init=False)
    _seen: dict[str, tuple[Principal, float]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        self.secret = self.secret or load_or_create_secret(self.settings.data_dir)
        self.throttle = Throttle(self.settings.login_attempts)

    @property
    def users_mode(self) -> bool:
        return self.settings.auth == "users"

    def check_ready(self) -> None:
        """Fail fast: the users mode with nobody who can log in."""
        if not self.users_mode:
            return
        with self.sessions() as s:
            active = s.scalars(select(User).where(User.disabled.is_(False))).first()
        if active is None:
            raise NoUsers(
                "MOSAIC_AUTH=users but no user is configured: add one with "
                "'mosaic-afm users add NAME --role admin' (it reads the password from stdin)"
            )

    # -- who a request comes from ------------------------------------------------------------

    def authenticate(
        self, authorization: str | None, cookie: str | None, operator: str | None
    ) -> Principal | None:
        """The principal of a request's ``Authorization`` header, else of its session cookie
        (users mode), else None. ``operator`` (``X-Operator``) names the person in the single
        mode."""
        scheme, _, given = (authorization or "").partition(" ")
        bearer = given.strip() if scheme.lower() == "bearer" else ""
        if not self.users_mode:
            if bearer and same(bearer, self.token):
                who = (operator or "").strip()[:64] or "api"
                return Principal(who, "admin", sc.ALL, 0, "token")
            return None
        if bearer:
            return self._remembered(bearer, cookie=False)
        if cookie:
            return self._remembered(cookie, cookie=True)
        return None

    def _remembered(self, secret: str, *, cookie: bool) -> Principal | None:
        key = digest(secret)
        now = time.time()
        with self._lock:
            seen = self._seen.get(key)
        if seen is not None and now < seen[1]:
            found = seen[0]
        else:
            looked = self._look_up(secret)
            if looked is None:
                return None
            found, ends = looked
            with self._lock:
                if len(self._seen) > 10_000:
                    self._seen.clear()
                self._seen[key] = (found, min(now + REMEMBER, ends))
        if cookie:
            found = Principal(**{**found.__dict__, "cookie": True})
        return found

    def forget(self) -> None:
        """Forget every identity looked up (something was revoked)."""
        with self._lock:
            self._seen.clear()

    def _look_up(self, secret: str) -> tuple[Principal, float] | None:
        """The principal of a key or access token, and when it ends (Unix seconds)."""
        prefix = key_prefix(secret)
        with self.sessions() as s:
            if prefix is not None:
                row = s.scalar(select(ApiKey).where(ApiKey.prefix == prefix))
                if (
                    row is None
                    or row.revoked_at is not None
                    or not same(row.key_hash, digest(secret))
                ):
                    return None
                if row.expires_at is not None and row.expires_at <= _now():
                    return None
                user = s.get(User, row.user_id)
                if user is None or user.disabled:
                    return None
                allowed = sc.role_scopes(user.role) & frozenset(row.scopes)
                ends = row.expires_at.timestamp() if row.expires_at is not None else math.inf
                return Principal(user.name, user.role, allowed, user.id, "key", key_id=row.id), ends
            read = read_access(self.secret, secret, time.time())
            if read is None:
                return None
            sid, expires = read
            login = s.get(LoginSession, sid)
            if login is None or login.revoked_at is not None or login.expires_at <= _now():
                return None
            user = s.get(User, login.user_id)
            if user is None or user.disabled:
                return None
            who = Principal(
                user.name, user.role, sc.role_scopes(user.role), user.id, "session", session_id=sid
            )
            return who, min(expires, login.expires_at.timestamp())

    # -- logins -------------------------------------------------------------------------------

    def login(self, name: str, password: str, address: str) -> Tokens:
        """A new session for ``name``; :class:`Refused` (401, or 429 while throttled)."""
        keys = (f"name:{name.lower()}", f"address:{address}")
        wait = self.throttle.wait(*keys)
        if wait > 0:
            raise Refused(
                429,
                f"too many failed logins for this name or address: try again in {wait:.0f} s",
                retry_after=wait,
            )
        with self.sessions() as s:
            user = s.scalar(select(User).where(User.name == name))
            ok = self._password_ok(user, name, password)
            if not ok or user is None or user.disabled:
                self.throttle.failed(*keys)
                raise Refused(401, "wrong user name or password")
            self.throttle.succeeded(*keys)
            return self._new_session(s, user, address)

    def _password_ok(self, user: User | None, name: str, password: str) -> bool:
        if user is None or user.provider == "local":
            return verify_password(password, user.password_hash if user is not None else None)
        try:
            ok, said = pam_login(
                name,
                password,
                service=self.settings.pam_service,
                confdir=self.settings.pam_confdir,
            )
        except PamUnavailable as exc:
            log.error("PAM login of %s: %s", name, exc)
            return False
        if not ok:
            log.info("PAM refused %s: %s", name, said)
        return ok

    def _new_session(self, s: Session, user: User, address: str) -> Tokens:
        login = LoginSession(
            user_id=user.id,
            expires_at=_now() + timedelta(seconds=self.settings.refresh_ttl),
            refresh_hash="",
            address=address[:64],
        )
        s.add(login)
        s.flush()
        return self._issue(s, login)

    def _issue(self, s: Session, login: LoginSession) -> Tokens:
        refresh, hashed = make_refresh(login.id)
        login.refresh_hash = hashed
        login.expires_at = _now() + timedelta(seconds=self.settings.refresh_ttl)
        s.commit()
        ttl = self.settings.access_ttl
        access = make_access(self.secret, login.id, int(time.time()) + ttl)
        return Tokens(access, refresh, ttl, login.id)

    def refresh(self, token: str) -> Tokens:
        """New tokens for a session, the refresh token replaced; :class:`Refused` (401)."""
        sid = refresh_session(token)
        with self.sessions() as s:
            login = s.get(LoginSession, sid) if sid is not None else None
            if (
                login is None
                or login.revoked_at is not None
                or login.expires_at <= _now()
                or not same(login.refresh_hash, digest(token))
            ):
                raise Refused(401, "this session has ended: log in again")
            user = s.get(User, login.user_id)
            if user is None or user.disabled:
                raise Refused(401, "this session has ended: log in again")
            return self._issue(s, login)

    def end_session(self, user_id: int, session_id: int) -> bool:
        """Revoke one of ``user_id``'s sessions; False if there is none such."""
        with self.sessions() as s:
            login = s.get(LoginSession, session_id)
            if login is None or login.user_id != user_id or login.revoked_at is not None:
                return False
            login.revoked_at = _now()
            s.commit()
        self.forget()
        return True

    def sessions_of(self, user_id: int) -> list[LoginSession]:
        with self.sessions() as s:
            rows = s.scalars(
                select(LoginSession)
                .where(LoginSession.user_id == user_id, LoginSession.revoked_at.is_(None))
                .where(LoginSession.expires_at > _now())
                .order_by(LoginSession.id)
            ).all()
            s.expunge_all()
            return list(rows)

    # -- keys ---------------------------------------------------------------------------------

    def create_key(
        self, who: Principal, scopes: list[str], expires_in: int | None, note: str
    ) -> tuple[ApiKey, str]:
        """A key for ``who`` with at most their scopes; :class:`Refused` (403) otherwise."""
        if who.via != "session":
            raise Refused(403, "API keys are made from a login session, not by a key or token")
        wanted = frozenset(scopes)
        unknown = wanted - sc.ALL
        if unknown:
            raise Refused(422, f"no such scope: {', '.join(sorted(unknown))}")
        beyond = wanted - who.scopes
        if beyond:
            raise Refused(
                403, f"a key can hold only your own scopes; you lack {', '.join(sorted(beyond))}"
            )
        key, prefix, hashed = make_key()
        with self.sessions() as s:
            row = ApiKey(
                user_id=who.user_id,
                prefix=prefix,
                key_hash=hashed,
                scopes=sorted(wanted),
                note=note,
                expires_at=_now() + timedelta(seconds=expires_in) if expires_in else None,
            )
            s.add(row)
            s.commit()
            s.refresh(row)
            s.expunge(row)
        return row, key

    def keys_of(self, user_id: int) -> list[ApiKey]:
        with self.sessions() as s:
            rows = s.scalars(select(ApiKey).where(ApiKey.user_id == user_id).order_by(ApiKey.id))
            out = list(rows.all())
            s.expunge_all()
            return out

    def revoke_key(self, who: Principal, key_id: int) -> bool:
        """Revoke a key of ``who``'s (an admin: anyone's); False if there is none such."""
        with self.sessions() as s:
            row = s.get(ApiKey, key_id)
            mine = row is not None and (row.user_id == who.user_id or sc.USERS in who.scopes)
            if row is None or not mine or row.revoked_at is not None:
                return False
            row.revoked_at = _now()
            s.commit()
        self.forget()
        return True

    # -- users --------------------------------------------------------------------------------

    def add_user(self, name: str, role: str, password: str | None, *, provider: str) -> User:
        """A new user; ValueError for a bad name, role, provider or password, or a name taken."""
        return add_user(self.sessions, name, role, password, provider=provider)

    def set_disabled(self, name: str, disabled: bool) -> bool:
        with self.sessions() as s:
            user = s.scalar(select(User).where(User.name == name))
            if user is None:
                return False
            user.disabled = disabled
            if disabled:
                end_sessions(s, user.id)
            s.commit()
        self.forget()
        return True


def end_sessions(s: Session, user_id: int) -> None:
    """End every login session of ``user_id`` (in ``s``, committed by the caller)."""
    for login in s.scalars(select(LoginSession).where(LoginSession.user_id == user_id)):
        login.revoked_at = login.revoked_at or _now()


def add_user(
    sessions: sessionmaker[Session], name: str, role: str, password: str | None, *, provider: str
) -> User:
    """Add a user to the database (the ``users`` command and the API share it)."""
    name = check_name(name)
    sc.role_scopes(role)
    if provider not in ("local", "pam"):
        raise ValueError(f"no login provider {provider!r}: local or pam")
    hashed = hash_password(password or "") if provider == "local" else None
    with sessions() as s:
        if s.scalar(select(User).where(User.name == name)) is not None:
            raise ValueError(f"there is already a user {name!r}")
        user = User(name=name, role=role, provider=provider, password_hash=hashed)
        s.add(user)
        s.commit()
        s.refresh(user)
        s.expunge(user)
        return user
