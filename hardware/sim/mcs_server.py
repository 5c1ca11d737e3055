"""The MCS protocol simulator as a TCP server, reached by pyserial as ``socket://host:port``.

Start it in-process for tests (``with MCSServer() as server: server.url``) or as a program
(``mosaic-afm sim-mcs --port P``). Faults can be injected to test what a driver does when the
link misbehaves: stop answering, answer garbage, answer an error code, drop the connection.

With a clock that runs as fast as possible, a read (``:GS``, ``:GP``, ``:GVL``) first moves
simulated time to the end of every running motion, so a client polling for "stopped" never
waits; every command also costs a millisecond of simulated time.
"""

from __future__ import annotations

import socket
import socketserver
import threading
from collections import deque
from dataclasses import dataclass
from io import BufferedIOBase
from types import TracebackType
from typing import Literal

from hardware.sim.clock import SimClock
from hardware.sim.mcs_device import MCSDevice

Fault = Literal["silent", "garbage", "error", "drop"]
_READS = ("GS", "GP", "GVL")


@dataclass
class _FaultState:
    mode: Fault | None = None
    code: int = 150
    remaining: int | None = None  # commands left to misbehave on; None: until healed

    def take(self) -> Fault | None:
        """The fault for the next command, counting it down."""
        mode = self.mode
        if mode is not None and self.remaining is not None:
            self.remaining -= 1
            if self.remaining <= 0:
                self.mode, self.remaining = None, None
        return mode


class MCSServer:
    """A TCP server speaking the MCS ASCII protocol for one simulated controller.

    Parameters
    ----------
    device : MCSDevice, optional
        The simulated controller (default: 3 channels).
    host, port : str, int
        Where to listen; port 0 picks a free one (read :attr:`url`).
    clock : SimClock, optional
        Simulated time (default: as fast as possible).
    """

    def __init__(
        self,
        device: MCSDevice | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        clock: SimClock | None = None,
    ) -> None:
        self.device = device or MCSDevice()
        self.clock = clock or SimClock(None)
        self.faults = _FaultState()
        self.lock = threading.Lock()
        #: the latest (command, reply) pairs, for transcripts and diagnosis (bounded)
        self.log: deque[tuple[str, str | None]] = deque(maxlen=10_000)
        server = self

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                server._serve(self.connection, self.rfile, self.wfile)

        class TCP(socketserver.ThreadingTCPServer):
            allow_reuse_address = True
            daemon_threads = True

        self._tcp = TCP((host, port), Handler)
        self._thread: threading.Thread | None = None

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._tcp.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        """The pyserial URL of this server."""
        host, port = self.address
        return f"socket://{host}:{port}"

    def start(self) -> MCSServer:
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

    def __enter__(self) -> MCSServer:
        return self.start()

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def inject(self, mode: Fault | None, *, code: int = 150, count: int | None = None) -> None:
        """Misbehave from the next command on (``None`` heals the link): for ``count``
        commands, or until healed when ``count`` is None."""
        if count is not None and count < 1:
            raise ValueError(f"count must be a positive number of commands, got {count}")
        with self.lock:
            self.faults.mode, self.faults.code = mode, code
            self.faults.remaining = count if mode is not None else None

    def _serve(self, conn: socket.socket, rfile: BufferedIOBase, wfile: BufferedIOBase) -> None:
        while True:
            try:
                raw = rfile.readline()
            except OSError:
                return
            if not raw:
                return
            line = raw.decode("ascii", errors="replace").strip()
            if not line:
                continue
            with self.lock:
                mode = self.faults.take()
            if mode == "drop":
                conn.shutdown(socket.SHUT_RDWR)
                conn.close()
                return
            with self.lock:
                if self.clock.fast:
                    self.clock.advance(0.001)
                    if line[1:].startswith(_READS):
                        self.clock.advance_to(self.device.busy_until(self.clock.now()))
                reply = self.device.handle(line, self.clock.now())
                self.log.append((line, reply))
            if mode == "silent":
                continue
            if mode == "garbage":
                reply = ":#?%\x07garbage"
            elif mode == "error":
                reply = f":E-1,{self.faults.code}"
            if reply is not None:
                try:
                    wfile.write((reply + "\n").encode("ascii", errors="replace"))
                except OSError:
                    return
