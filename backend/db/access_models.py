"""Who may do what, and what they did: users, their login sessions and API keys, the operator
lock and the audit trail (migration 0007). Secrets are never stored, only their hashes."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import JSON, Boolean, ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from backend.db.models import Base, UTCDateTime, utcnow


class User(Base):
    """A person who logs in: by a local password (Argon2) or by the host's PAM."""

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    name: Mapped[str] = mapped_column(String(64), unique=True, index=True)
    #: ``observer``, ``operator`` or ``admin``
    role: Mapped[str] = mapped_column(String(16))
    #: ``local`` (``password_hash`` holds the Argon2 hash) or ``pam``
    provider: Mapped[str] = mapped_column(String(16), default="local")
    password_hash: Mapped[str | None] = mapped_column(String(256), nullable=True)
    disabled: Mapped[bool] = mapped_column(Boolean, default=False)


class LoginSession(Base):
    """A login: its refresh token's hash (rotated at every refresh) and when it ends."""

    __tablename__ = "login_sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime())
    refresh_hash: Mapped[str] = mapped_column(String(64))
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    address: Mapped[str] = mapped_column(String(64), default="")


class ApiKey(Base):
    """A script's key: acts for its user with at most ``scopes``; found by ``prefix``."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    prefix: Mapped[str] = mapped_column(String(16), unique=True, index=True)
    key_hash: Mapped[str] = mapped_column(String(64))
    scopes: Mapped[list[str]] = mapped_column(JSON, default=list)
    note: Mapped[str] = mapped_column(String(200), default="")
    expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime(), nullable=True)


class LockRecord(Base):
    """The operator lock (one row, id 1, while held): who holds the instrument and why."""

    __tablename__ = "instrument_lock"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    since: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    #: the holder's user id; 0 for the single-user mode's one identity
    holder_id: Mapped[int] = mapped_column(Integer)
    holder: Mapped[str] = mapped_column(String(64))
    note: Mapped[str] = mapped_column(String(500), default="")


class AuditRecord(Base):
    """One state change asked for: who, when, from where, what, and how it ended. Written by
    the server only; the API has no route that changes or removes one."""

    __tablename__ = "audit"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow, index=True)
    user: Mapped[str] = mapped_column(String(64), index=True)
    address: Mapped[str] = mapped_column(String(64), default="")
    #: the route's name (``start_run``, ``login``, ``break_lock``, ...)
    action: Mapped[str] = mapped_column(String(64))
    #: the request's method and path (``POST /api/runs/3/start``)
    target: Mapped[str] = mapped_column(String(300))
    run_id: Mapped[int | None] = mapped_column(Integer, nullable=True, index=True)
    #: ``ok``, ``refused`` (authentication, scope, lock, throttle) or ``failed``
    outcome: Mapped[str] = mapped_column(String(16))
    status: Mapped[int] = mapped_column(Integer)
    detail: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
