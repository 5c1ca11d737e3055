"""What the protocol simulators share: a threaded TCP server and link faults to inject.

Each simulator (:mod:`hardware.sim.mcs_server`, :mod:`hardware.sim.nanonis_server`) subclasses
:class:`TCPService` with the conversation of its own wire protocol (:meth:`TCPService.serve`);
this module holds the listening, the start and stop, and the fault that the next requests
suffer (``mode`` for ``count`` requests, or until healed).
"""

from __future__ import annotations

import contextlib
import socket
import socketserver
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Generic, Protocol, Self, TypeVar

Mode = TypeVar("Mode", bound=str)


@dataclass
class FaultState(Generic[Mode]):
    """The link fault in force: its mode, the error code it answers, requests left."""

    mode: Mode | None = None
    code: int = 0
    remaining: int | None = None  # requests left to misbehave on; None: until healed

    def take(self) -> Mode | None:
        """The fault for the next request, counting it down."""
        mode = self.mode
        if mode is not None and self.remaining is not None:
            self.remaining -= 1
            if self.remaining <= 0:
                self.mode, self.remaining = None, None
        return mode


class TCPService(ABC, Generic[Mode]):
    """A threaded TCP server on ``host:port`` (0 picks a free port) that hands every
    connection to :meth:`serve`, with a :class:`FaultState` for :meth:`inject` (an injected
    ``error`` answers ``code`` unless the injection names another)."""

    def __init__(self, *, host: str, port: int, code: int) -> None:
        self.default_code = code
        self.faults: FaultState[Mode] = FaultState(code=code)
        self.lock = threading.Lock()
        service = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                service.serve(self)

        class TCP(socketserver.ThreadingTCPServer):
            allow_reuse_address = True
            daemon_threads = True

        self._tcp = TCP((host, port), Handler)
        self._thread: threading.Thread | None = None

    @abstractmethod
    def serve(self, handler: socketserver.StreamRequestHandler) -> None:
        """One connection's conversation (``handler.connection``, ``rfile``, ``wfile``)."""

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._tcp.server_address[:2]
        return str(host), int(port)

    def start(self) -> Self:
        self._thread = threading.Thread(
            target=self._tcp.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
        )
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        self._tcp.serve_forever(poll_interval=0.05)

    def stop(self) -> None:
        self._tcp.shutdown()
        self._tcp.server_close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def inject(
        self, mode: Mode | None, *, code: int | None = None, count: int | None = None
    ) -> None:
        """Misbehave from the next request on (``None`` heals the link): for ``count``
        requests, or until healed when ``count`` is None."""
        if count is not None and count < 1:
            raise ValueError(f"count must be a positive number of requests, got {count}")
        with self.lock:
            self.faults.mode = mode
            self.faults.code = self.default_code if code is None else code
            self.faults.remaining = count if mode is not None else None

    def take_fault(self) -> Mode | None:
        with self.lock:
            return self.faults.take()


def close_connection(conn: socket.socket) -> None:
    """Shut a connection down both ways and close it (a dropped link)."""
    with contextlib.suppress(OSError):
        conn.shutdown(socket.SHUT_RDWR)
    conn.close()


def recv_exact(conn: socket.socket, n: int) -> bytes | None:
    """Exactly ``n`` bytes from ``conn``, or None when the peer closed it first."""
    chunks, got = [], 0
    while got < n:
        chunk = conn.recv(min(n - got, 1 << 20))
        if not chunk:
            return None
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


class _Sized(Protocol):
    @property
    def body_size(self) -> int: ...


H = TypeVar("H", bound=_Sized)


def receive_message(
    conn: socket.socket,
    header_size: int,
    decode: Callable[[bytes], H],
    garbled: type[Exception],
) -> tuple[H, bytes] | None:
    """The next whole message on ``conn``: its header (``decode`` of ``header_size`` bytes)
    and body; None when the peer closed, or when the stream is out of step (a ``garbled``
    header, a link error): a simulator closes the connection then, as it cannot resynchronise."""
    try:
        head = recv_exact(conn, header_size)
        if head is None:
            return None
        header = decode(head)
        body = recv_exact(conn, header.body_size)
    except (OSError, garbled):
        conn.close()
        return None
    return None if body is None else (header, body)
