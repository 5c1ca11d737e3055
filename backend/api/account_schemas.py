"""Request and response bodies of logins, keys, the lock, the audit trail and users."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from backend.security import scopes as sc


class _In(BaseModel):
    """A request body that refuses fields it does not know."""

    model_config = ConfigDict(extra="forbid")


class LoginIn(_In):
    """A login by name and password (``cookie``: the browser's, tokens in HttpOnly cookies)."""

    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=1024)
    cookie: bool = Field(
        default=False,
        description="the browser's login: the tokens go in HttpOnly cookies, not the answer",
    )


class RefreshIn(_In):
    """A session's refresh token (absent: the browser's refresh cookie)."""

    refresh_token: str | None = Field(
        default=None, max_length=200, description="absent: the browser's refresh cookie"
    )


class TokensOut(BaseModel):
    """A login's tokens: a short-lived access token and the refresh token that renews it."""

    access_token: str | None = Field(description="None for a cookie login")
    refresh_token: str | None = Field(description="None for a cookie login")
    expires_in: int = Field(description="seconds the access token lives")
    token_type: str = "bearer"
    csrf_token: str | None = Field(
        default=None, description="a cookie login's: echo it in X-CSRF-Token on every change"
    )


class WhoOut(BaseModel):
    """Who a request is from, and the server's mode."""

    mode: Literal["single", "users"]
    user: str | None = Field(description="None: nobody identified")
    role: str | None
    scopes: list[str]
    via: str | None = Field(description="token, session, key or anonymous")
    anonymous_read: bool


class SessionOut(BaseModel):
    """One of the caller's login sessions that has not ended."""

    id: int
    created_at: datetime
    expires_at: datetime
    address: str
    current: bool


class KeyIn(_In):
    """A new API key: its scopes (a subset of the caller's), life and note."""

    scopes: list[str] = Field(min_length=1, max_length=len(sc.ALL), description="a subset of yours")
    expires_in: int | None = Field(
        default=None, gt=0, le=10 * 365 * 86400, description="seconds; None: until revoked"
    )
    note: str = Field(default="", max_length=200)


class KeyOut(BaseModel):
    """An API key as listed: its prefix only, never the key."""

    id: int
    prefix: str = Field(description="the key's first characters (the rest is shown once)")
    scopes: list[str]
    note: str
    created_at: datetime
    expires_at: datetime | None
    revoked: bool


class NewKeyOut(BaseModel):
    """A new API key, shown this once."""

    id: int
    key: str = Field(description="the key itself: shown this once, never again")
    prefix: str
    scopes: list[str]
    expires_at: datetime | None


class LockIn(_In):
    """Take (or keep) the operator lock, with a note others see."""

    note: str = Field(default="", max_length=500)


class UnlockIn(_In):
    """Release the lock; an admin breaking another's gives the reason."""

    reason: str = Field(default="", max_length=500, description="an admin breaking the lock")


class LockOut(BaseModel):
    """Who holds the instrument, since when, why, and whether it is the caller."""

    held: bool
    holder: str | None
    note: str | None
    since: datetime | None
    yours: bool


class AuditOut(BaseModel):
    """One row of the audit trail."""

    id: int
    at: datetime
    user: str
    address: str
    action: str
    target: str
    run_id: int | None
    outcome: str
    status: int
    detail: dict[str, Any]


class UserIn(_In):
    """A new user: name, role and login provider (a local user's password)."""

    name: str = Field(min_length=1, max_length=64)
    role: Literal["observer", "operator", "admin"]
    password: str | None = Field(default=None, max_length=1024, description="local users")
    provider: Literal["local", "pam"] = "local"


class UserOut(BaseModel):
    """A user as listed (never a password or its hash)."""

    name: str
    role: str
    provider: str
    disabled: bool
    created_at: datetime
