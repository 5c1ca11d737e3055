"""Who may open the 3D viewer: a browser on a page of this server, holding the API token.

The viewer listens on its own port. A browser proves the token with a cookie the API sets
(``POST /api/instrument/viewer/session``, with the token; HttpOnly, SameSite=Strict): cookies
go to every port of a host, so the viewer's handshake carries it, and a frame on another
site's page does not. The handshake's origin must be the viewer's own page or the API's on
the same host (or a configured CORS origin): another site's script cannot open the viewer's
websocket in a visitor's browser.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable, Mapping
from http.cookies import CookieError, SimpleCookie
from urllib.parse import urlsplit

#: The cookie that carries a browser's right to the viewer.
COOKIE = "mosaic_viewer"


def viewer_key(token: str) -> str:
    """What the cookie holds: derived from the API token, never the token itself."""
    return hmac.new(token.encode(), b"mosaic-afm viewer", hashlib.sha256).hexdigest()


def _host_port(header: str, default: int) -> tuple[str, int]:
    parts = urlsplit(f"//{header}")
    return parts.hostname or "", parts.port or default


def admission(
    *, token: str, api_port: int, origins: list[str]
) -> Callable[[Mapping[str, str]], str | None]:
    """The viewer's check of a websocket handshake's ``headers``: None to admit, else why.
    The origin must be the viewer's own page (the host and port the handshake names: its
    page in the operator's frame) or the API's page on that host, or a configured origin."""
    key = viewer_key(token)
    allowed = {o.rstrip("/") for o in origins}

    def admit(headers: Mapping[str, str]) -> str | None:
        origin = (headers.get("Origin") or "").rstrip("/")
        parts = urlsplit(origin)
        scheme_port = 443 if parts.scheme == "https" else 80
        host, port = _host_port(headers.get("Host") or "", scheme_port)
        same = (
            parts.scheme in ("http", "https")
            and parts.hostname is not None
            and parts.hostname == host
            and (parts.port or scheme_port) in (port, api_port)
        )
        if not same and origin not in allowed:
            return f"origin {origin[:80]!r} is not this server's page"
        try:
            jar = SimpleCookie(headers.get("Cookie") or "")
        except CookieError:
            return "a cookie header that does not parse"
        given = jar[COOKIE].value if COOKIE in jar else ""
        if not hmac.compare_digest(given.encode(), key.encode()):
            return "no viewer session: enter the API token on the page"
        return None

    return admit
