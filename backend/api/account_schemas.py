"""Request and response bodies of logins, keys, the lock, the audit trail and users."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from backend.security import scopes as sc


class _In(BaseModel):
    model_config = ConfigDict(extra="forbid")


class LoginIn(_In):
    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=1024)
    cookie: bool = Field(
        default=False,
        description="the browser's login: the tokens go in HttpOnly cookies, not the answer",
    )


class RefreshIn(_In):
    refresh_token: str | None = Field(
        default=None, max_length=200, description="absent: the browser's refresh cookie"
    )


class TokensOut(BaseModel):
    access_token: str | None = Field(description="None for a cookie login")
    refresh_token: str | None = Field(description="None for a cookie login")
    expires_in: int = Field(description="seconds the access token lives")
    token_type: str = "bearer"
    csrf_token: str | None = Field(
        default=None, description="a cookie login's: echo it in X-CSRF-Token on every change"
    )


class WhoOut(BaseModel):
    mode: Literal["single", "users"]
    user: str | None = Field(description="None: nobody identified")
    role: str | None
    scopes: list[str]
    via: str | None = Field(description="token, session, key or anonymous")
    anonymous_read: bool


class SessionOut(BaseModel):
    id: int
    created_at: datetime
    expires_at: datetime
    address: str
    current: bool


class KeyIn(_In):
    scopes: list[str] = Field(min_length=1, max_length=len(sc.ALL), description="a subset of yours")
    expires_in: int | None = Field(
        default=None, gt=0, le=10 * 365 * 86400, description="seconds; None: until revoked"
    )
    note: str = Field(default="", max_length=200)


class KeyOut(BaseModel):
    id: int
    prefix: str = Field(description="the key's first characters (the rest is shown once)")
    scopes: list[str]
    note: str
    created_at: datetime
    expires_at: datetime | None
    revoked: bool


class NewKeyOut(BaseModel):
    id: int
    key: str = Field(description="the key itself: shown this once, never again")
    prefix: str
    scopes: list[str]
    expires_at: datetime | None


class LockIn(_In):
    note: str = Field(default="", max_length=500)


class UnlockIn(_In):
    reason: str = Field(default="", max_length=500, description="an admin breaking the lock")


class LockOut(BaseModel):
    held: bool
    holder: str | None
    note: str | None
    since: datetime | None
    yours: bool


class AuditOut(BaseModel):
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
    name: str = Field(min_length=1, max_length=64)
    role: Literal["observer", "operator", "admin"]
    password: str | None = Field(default=None, max_length=1024, description="local users")
    provider: Literal["local", "pam"] = "local"


class UserOut(BaseModel):
    name: str
    role: str
    provider: str
    disabled: bool
    created_at: datetime
