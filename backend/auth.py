"""The API token: from ``MOSAIC_API_TOKEN``, else generated once and kept in the data dir."""

from __future__ import annotations

import os
import secrets
from pathlib import Path

from backend.settings import Settings

TOKEN_FILE = "api_token"


def load_or_create_token(settings: Settings) -> tuple[str, bool]:
    """The bearer token for changes, and whether it was just generated (print it once)."""
    if settings.api_token is not None:
        return settings.api_token.get_secret_value(), False
    path: Path = settings.data_dir / TOKEN_FILE
    if path.exists():
        token = path.read_text(encoding="utf-8").strip()
        if token:
            return token, False
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(token + "\n")
    return token, True


def token_matches(given: str, expected: str) -> bool:
    return secrets.compare_digest(given.encode(), expected.encode())
