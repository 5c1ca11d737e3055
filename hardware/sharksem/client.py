"""The link to a TESCAN SEM: a control connection (requests and replies) and a data connection
(the images it streams), as SharkSEM has them.

The control connection goes to the SEM's port (8300 by default); the data connection to the
port after it, and the SEM is told which local port it comes from (``TcpRegDataPort``). A
request that wants a reply carries :data:`~hardware.sharksem.wire.RESPOND` and a message id
the reply repeats; every failure is a typed :mod:`~hardware.sharksem.errors` error naming the
command, and a link that failed is closed (the next command says so).
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Sequence
from types import TracebackType
from typing import Any, Self

from hardware.sharksem.errors import SharkSEMLinkError, SharkSEMProtocolError, SharkSEMTimeout
from hardware.sharksem.wire import HEADER_SIZE, RESPOND, Header, decode, decode_header, message

#: The SEM's default control port.
PORT = 8300


class Link:
    """One TCP connection that sends and receives whole messages."""

    def __init__(self, sock: socket.socket, name: str) -> None:
        self.sock = sock
        self.name = name

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except TimeoutError:
            raise SharkSEMTimeout(f"{self.name}: sending timed out") from None
        except OSError as exc:
            raise SharkSEMLinkError(
                f"{self.name}: the link dropped while sending ({exc})"
            ) from None

    def _exactly(self, n: int, what: str) -> bytes:
        chunks, got = [], 0
        while got < n:
            try:
                chunk = self.sock.recv(min(n - got, 1 << 20))
            except TimeoutError:
                raise SharkSEMTimeout(f"{self.name}: no answer to {what} in time") from None
            except OSError as exc:
                raise SharkSEMLinkError(
                    f"{self.name}: the link dropped during {what} ({exc})"
                ) from None
            if not chunk:
                raise SharkSEMLinkError(f"{self.name}: the SEM closed the link during {what}")
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)

    def receive(self, what: str) -> tuple[Header, bytes]:
        """The next whole message: its header and body."""
        header = decode_header(self._exactly(HEADER_SIZE, what))
        return header, self._exactly(header.body_size, what)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


class SharkSEMClient:
    """Requests and replies on the control link, images on the data link.

    Parameters
    ----------
    control, data : Link
        The two connections (:meth:`open` makes them).
    """

    def __init__(self, control: Link, data: Link | None = None) -> None:
        self.control = control
        self.data = data
        self._ids = 0
        self._lock = threading.Lock()
        self.broken: str | None = None

    @classmethod
    def open(cls, host: str, port: int = PORT, *, timeout: float = 10.0) -> SharkSEMClient:
        """Connect the control link to ``host:port`` and the data link to ``port + 1``, and
        register the data link's local port with the SEM."""
        links = []
        try:
            for p, name in ((port, "SEM control"), (port + 1, "SEM data")):
                sock = socket.create_connection((host, p), timeout=timeout)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                links.append(Link(sock, f"{name} {host}:{p}"))
        except OSError as exc:
            for link in links:
                link.close()
            raise SharkSEMLinkError(
                f"cannot reach the SEM at {host}:{port} and {port + 1} ({exc}): is SharkSEM "
                "remote control enabled and the ports open?"
            ) from None
        client = cls(links[0], links[1])
        client.call("TcpRegDataPort", "i", [links[1].sock.getsockname()[1]])
        return client

    def call(
        self, command: str, types: str = "", values: Sequence[Any] = (), reply: str = ""
    ) -> list[Any]:
        """Send ``command`` with ``values`` of ``types``; with ``reply`` types, wait for the
        reply (same command, same message id) and return its fields, else return []."""
        with self._lock:
            if self.broken is not None:
                raise SharkSEMLinkError(f"{command}: the SEM link is down ({self.broken})")
            self._ids = (self._ids + 1) % (1 << 32)
            message_id = self._ids
            flags = RESPOND if reply else 0
            try:
                sent = message(command, types, values, message_id=message_id, flags=flags)
                self.control.send(sent)
                if not reply:
                    return []
                header, body = self.control.receive(command)
            except (SharkSEMLinkError, SharkSEMTimeout, SharkSEMProtocolError) as exc:
                self.fail(str(exc))
                raise
            if header.command != command or header.message_id != message_id:
                problem = (
                    f"{command}: the reply is {header.command!r} #{header.message_id}, not to "
                    f"this request (#{message_id})"
                )
                self.fail(problem)
                raise SharkSEMProtocolError(problem)
            try:
                return decode(reply, body, what=f"reply to {command}")
            except SharkSEMProtocolError as exc:
                self.fail(str(exc))
                raise

    def receive_data(self, what: str) -> tuple[Header, bytes]:
        """The next message on the data link (``ScData``: a block of an image's pixels)."""
        if self.data is None:
            raise SharkSEMLinkError(f"{what}: no data link to the SEM")
        try:
            return self.data.receive(what)
        except (SharkSEMLinkError, SharkSEMTimeout, SharkSEMProtocolError) as exc:
            self.fail(str(exc))
            raise

    def fail(self, why: str) -> None:
        """A failed link is closed: what comes after it cannot be trusted to line up."""
        self.broken = why
        self.close()

    def close(self) -> None:
        self.control.close()
        if self.data is not None:
            self.data.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
