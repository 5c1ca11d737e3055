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
from collections import deque
from io import BufferedIOBase
from typing import Literal

from hardware.sim.clock import SimClock
from hardware.sim.mcs_device import MCSDevice
from hardware.sim.tcp_service import TCPService, close_connection

Fault = Literal["silent", "garbage", "error", "drop"]
_READS = ("GS", "GP", "GVL")


class MCSServer(TCPService[Fault]):
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
        super().__init__(host=host, port=port, code=150)
        self.device = device or MCSDevice()
        self.clock = clock or SimClock(None)
        #: the latest (command, reply) pairs, for transcripts and diagnosis (bounded)
        self.log: deque[tuple[str, str | None]] = deque(maxlen=10_000)

    @property
    def url(self) -> str:
        """The pyserial URL of this server."""
        host, port = self.address
        return f"socket://{host}:{port}"

    def serve(self, handler: socketserver.StreamRequestHandler) -> None:
        self._serve(handler.connection, handler.rfile, handler.wfile)

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
            mode = self.take_fault()
            if mode == "drop":
                close_connection(conn)
                return
            # Time moves on demand (hardware.sim.clock): a command takes a millisecond, and a
            # read first waits for what the device is busy with, the device not held meanwhile
            # (a stop from another link is heard).
            read = line[1:].startswith(_READS)
            with self.lock:
                self.clock.advance(0.001)
                busy = self.device.busy_until(self.clock.now()) if read else 0.0
            if read:
                self.clock.advance_to(busy)
            with self.lock:
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
