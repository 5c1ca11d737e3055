"""The secrets a request carries, made and checked: signed access tokens, refresh tokens and
API keys. Only hashes are stored; a token is never logged.

- access token ``mat.<session>.<expiry>.<signature>``: HMAC-SHA256 under the server's secret
  (a file of the data directory, readable by its owner only); short-lived, and refused once
  its session is revoked;
- refresh token ``mrt.<session>.<random>``: its SHA-256 kept on the session, replaced at each
  refresh (an old one refused);
- API key ``mak_<prefix>_<random>``: found by its prefix (the only part shown after it is
  made), checked against its SHA-256.

These are 256-bit random secrets, not passwords: a fast hash keeps them safe at rest.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import secrets
from pathlib import Path

SECRET_FILE = "auth_secret"
ACCESS = "mat"
REFRESH = "mrt"
KEY = "mak"


def digest(secret: str) -> str:
    """The stored form of a random secret: its SHA-256, hex."""
    return hashlib.sha256(secret.encode()).hexdigest()


def same(a: str, b: str) -> bool:
    return hmac.compare_digest(a.encode(), b.encode())


def load_or_create_secret(data_dir: Path) -> bytes:
    """The server's signing secret: read from ``data_dir/auth_secret``, or made there (0600)."""
    path = data_dir / SECRET_FILE
    if path.exists():
        text = path.read_text(encoding="ascii").strip()
        if len(text) >= 43:
            return text.encode()
    data_dir.mkdir(parents=True, exist_ok=True)
    text = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(text + "\n")
    return text.encode()


def sign(secret: bytes, payload: str) -> str:
    mac = hmac.new(secret, payload.encode(), hashlib.sha256).digest()
    return base64.urlsafe_b64encode(mac).rstrip(b"=").decode()


def make_access(secret: bytes, session_id: int, expires: int) -> str:
    """An access token for ``session_id`` valid until ``expires`` (Unix seconds)."""
    payload = f"{ACCESS}.{session_id}.{expires}"
    return f"{payload}.{sign(secret, payload)}"


def read_access(secret: bytes, token: str, now: float) -> tuple[int, int] | None:
    """The session id an access token stands for and its expiry (Unix seconds), or None
    (forged, malformed or expired)."""
    parts = token.split(".")
    if len(parts) != 4 or parts[0] != ACCESS or not parts[1].isdigit() or not parts[2].isdigit():
        return None
    payload = ".".join(parts[:3])
    if not same(parts[3], sign(secret, payload)) or int(parts[2]) <= now:
        return None
    return int(parts[1]), int(parts[2])


def make_refresh(session_id: int) -> tuple[str, str]:
    """A refresh token for ``session_id`` and the hash to store."""
    token = f"{REFRESH}.{session_id}.{secrets.token_urlsafe(32)}"
    return token, digest(token)


def refresh_session(token: str) -> int | None:
    """The session a refresh token names (checked against its stored hash by the caller)."""
    parts = token.split(".")
    if len(parts) != 3 or parts[0] != REFRESH or not parts[1].isdigit():
        return None
    return int(parts[1])


def make_key() -> tuple[str, str, str]:
    """A new API key: ``(key, prefix, hash)``; the key is shown once, the rest stored."""
    prefix = secrets.token_hex(4)
    key = f"{KEY}_{prefix}_{secrets.token_urlsafe(32)}"
    return key, prefix, digest(key)


def key_prefix(key: str) -> str | None:
    """The prefix of something shaped as an API key, else None."""
    parts = key.split("_", 2)
    if len(parts) != 3 or parts[0] != KEY or len(parts[1]) != 8:
        return None
    return parts[1]
