"""``sem=sharksem://HOST:PORT``: the SEM part of an instrument URL, a TESCAN SEM over SharkSEM.

It composes with the AFM's parts (``nanonis://HOST:PORT?stage=mcs:URL&sem=sharksem://HOST:8300``,
``mcs://stage=URL;robot=URL;sem=sharksem://HOST:8300``). The control port is the one opened in
the SEM's remote-control settings (8300 by default); images come on the port after it.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from hardware.sharksem.client import PORT
from hardware.sharksem.errors import SharkSEMError
from hardware.sharksem.sem import TescanSEM


class SEMConfigurationError(ValueError):
    """An SEM URL that names no SEM one can reach; the message says what to write."""


def open_sem(url: str, *, timeout: float = 10.0) -> TescanSEM:
    """Connect to the SEM ``url`` names (``sharksem://HOST[:PORT]``)."""
    parts = urlsplit(url)
    try:
        host, port = parts.hostname, parts.port or PORT
    except ValueError:
        host, port = None, 0
    if parts.scheme != "sharksem" or not host or not 1 <= port <= 65534 or parts.query:
        raise SEMConfigurationError(
            f"sem={url!r}: give the SEM as sharksem://HOST:PORT (its SharkSEM control port, "
            f"{PORT} by default; images come on PORT + 1)"
        )
    try:
        return TescanSEM.connect(host, port, timeout=timeout)
    except SharkSEMError as exc:
        raise SEMConfigurationError(
            f"sem={url}: {exc}; is the SEM's remote control on, and are ports {port} and "
            f"{port + 1} open to this computer?"
        ) from None
