"""The simulated TESCAN SEM as SharkSEM serves it: a control port and a data port after it.

It answers what :class:`~hardware.sharksem.sem.TescanSEM` asks (``TcpRegDataPort``,
``TcpGetVersion``, ``GetViewField``, ``SetViewField``, ``StgGetPosition``,
``DtEnumDetectors``, ``DtSelect``, ``DtEnable``, ``EnumGeometries``, ``GetGeometry``,
``SetGeometry``, ``ScScanXY``, ``ScStopScan``) and streams every frame's pixels as ``ScData``
messages on the data link, in blocks. Its images are the simulated SEM's
(:meth:`hardware.sim.sem.SimulatedSEM.acquire`: through its true geometry, rotated and scaled
against the sample stage, with charging drift between frames).

Faults, injected as on the other simulators, for ``count`` requests or until healed: ``drop``
(the control link closes), ``silent`` (no reply), ``garbage`` (a reply that does not parse),
and on the next frame ``short`` (the data stop halfway) or ``drop_data`` (the data link closes
halfway).
"""

from __future__ import annotations

import socket
import socketserver
import threading
from collections import deque
from typing import Any, Literal

import numpy as np

from hardware.sharksem import wire
from hardware.sharksem.errors import SharkSEMProtocolError
from hardware.sim.sem import SimulatedSEM
from hardware.sim.tcp_service import TCPService, close_connection, receive_message

LinkFault = Literal["drop", "silent", "garbage", "short", "drop_data"]

#: Pixels an ``ScData`` message carries at most.
BLOCK = 64 * 1024
DETECTORS = ("SE", "BSE", "InBeam")
VERSION = "SharkSEM simulator 3.2.20"


class _DataPort(TCPService[str]):
    """The data port: it keeps the connections the client opened, by their remote port."""

    def __init__(self, *, host: str, port: int) -> None:
        super().__init__(host=host, port=port, code=0)
        self.links: dict[int, socket.socket] = {}
        self.ready = threading.Condition()

    def serve(self, handler: socketserver.StreamRequestHandler) -> None:
        conn = handler.connection
        with self.ready:
            self.links[conn.getpeername()[1]] = conn
            self.ready.notify_all()
        while True:  # held open for the images; nothing comes this way
            try:
                if not conn.recv(4096):
                    break
            except OSError:
                break
        with self.ready:
            self.links = {p: c for p, c in self.links.items() if c is not conn}


class SharkSEMServer(TCPService[LinkFault]):
    """A TCP server speaking SharkSEM over a simulated SEM.

    Parameters
    ----------
    sem : SimulatedSEM
        What the SEM sees (its sample, and how its scan sits over the stage: its geometry).
    host, port : str, int
        The control port (0 picks a free one); the data port is the next one up.
    stage : (x, y, z)
        The SEM stage's position, metres.
    """

    def __init__(
        self,
        sem: SimulatedSEM,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        stage: tuple[float, float, float] = (0.0, 0.0, 0.01),
    ) -> None:
        for _ in range(50):  # the data port is the control port + 1: find a free pair
            super().__init__(host=host, port=port, code=0)
            try:
                self.data_port = _DataPort(host=host, port=self.address[1] + 1)
                break
            except OSError:
                self._tcp.server_close()
                if port:
                    raise
        self.sem = sem
        self.stage = stage
        self.field = 50e-6
        self.detector: int | None = None
        self.enabled = False
        self.scan_rotation = 0.0
        self.world = threading.Lock()
        #: the commands served, for diagnosis and the transcript tests (bounded)
        self.log: deque[str] = deque(maxlen=10_000)
        self._registered: int | None = None

    @property
    def url(self) -> str:
        host, port = self.address
        return f"sharksem://{host}:{port}"

    def start(self) -> SharkSEMServer:
        self.data_port.start()
        super().start()
        return self

    def serve_forever(self) -> None:
        """Serve in this thread (the data port in its own) until stopped."""
        self.data_port.start()
        super().serve_forever()

    def stop(self) -> None:
        super().stop()
        self.data_port.stop()

    # -- serving ----------------------------------------------------------------------------

    def serve(self, handler: socketserver.StreamRequestHandler) -> None:
        conn = handler.connection
        while True:
            got = receive_message(conn, wire.HEADER_SIZE, wire.decode_header, SharkSEMProtocolError)
            if got is None:
                return
            header, body = got
            mode = self.take_fault()
            if mode == "drop":
                close_connection(conn)
                return
            self.log.append(header.command)
            try:
                types, values, after = self._handle(header.command, body, mode)
            except (SharkSEMProtocolError, ValueError):
                types, values, after = None, [], None  # a request it cannot read: no reply
            if header.respond and types is not None and mode != "silent":
                reply = wire.message(
                    header.command, types, values, message_id=header.message_id, flags=0
                )
                if mode == "garbage":
                    reply = b"\x07garbled\x00" * 4
                try:
                    conn.sendall(reply)
                except OSError:
                    return
            if after is not None:
                after()

    def _handle(self, command: str, body: bytes, mode: LinkFault | None) -> tuple[Any, Any, Any]:
        """The reply's types and values to ``command`` (types None: the SEM knows no such
        command, and does not answer), and what to do once the reply is sent."""
        with self.world:
            if command == "TcpRegDataPort":
                (self._registered,) = wire.decode("i", body, what=command)
                return "", [], None
            if command == "TcpGetVersion":
                return "s", [VERSION], None
            if command == "GetViewField":
                return "f", [self.field * 1e3], None
            if command == "SetViewField":
                (field_mm,) = wire.decode("f", body, what=command)
                if not 1e-6 <= field_mm <= 10.0:
                    raise ValueError(f"view field {field_mm} mm")
                self.field = field_mm * 1e-3
                return "", [], None
            if command == "StgGetPosition":
                x, y, z = self.stage
                return "fffff", [x * 1e3, y * 1e3, z * 1e3, 0.0, 0.0], None
            if command == "DtEnumDetectors":
                text = "".join(f"det.{k}.name={n}\ndet.{k}.detector={k}\n"
                               for k, n in enumerate(DETECTORS))  # fmt: skip
                return "s", [text], None
            if command == "DtSelect":
                _, self.detector = wire.decode("ii", body, what=command)
                return "", [], None
            if command == "DtEnable":
                _, enable, _ = wire.decode("iii", body, what=command)
                self.enabled = bool(enable)
                return "", [], None
            if command == "EnumGeometries":
                return "s", ["geom.0.name=ImageShift\ngeom.1.name=Rotation\n"], None
            if command == "GetGeometry":
                (index,) = wire.decode("i", body, what=command)
                return "ff", [self.scan_rotation if index == 1 else 0.0, 0.0], None
            if command == "SetGeometry":
                index, x, _ = wire.decode("iff", body, what=command)
                if index == 1:
                    self.scan_rotation = float(x)
                return "", [], None
            if command == "ScStopScan":
                return "", [], None
            if command == "ScScanXY":
                return self._scan(body, mode)
        return None, [], None

    def _scan(self, body: bytes, mode: LinkFault | None) -> tuple[Any, Any, Any]:
        frame_id, width, height, left, top, right, bottom, _, dwell_ns = wire.decode(
            "IIIIIIIiI", body, what="ScScanXY"
        )
        if (
            width != height
            or not 8 <= width <= 8192
            or (left, top, right, bottom) != (0, 0, width - 1, height - 1)
            or not self.enabled
            or self.detector is None
        ):
            return "i", [-1], None  # a square full frame on an enabled detector only
        frame = self.sem.acquire(
            field=self.field,
            pixels=width,
            dwell=min(max(dwell_ns, 10), 1_000_000) * 1e-9,
            detector=DETECTORS[self.detector % len(DETECTORS)],
            scan_rotation=self.scan_rotation,
        )
        image = frame.pixels
        lo, hi = np.percentile(image, [0.5, 99.5])
        grey = np.clip((image - lo) / max(hi - lo, 1e-12) * 255 + 0.5, 0, 255).astype(np.uint8)
        return "i", [0], lambda: self._stream(frame_id, grey.ravel(), mode)

    def _stream(self, frame_id: int, pixels: np.ndarray, mode: LinkFault | None) -> None:
        """Send a frame on the registered data link in ``ScData`` blocks."""
        with self.data_port.ready:
            self.data_port.ready.wait_for(lambda: self._registered in self.data_port.links, 5)
            conn = self.data_port.links.get(self._registered or -1)
        if conn is None:
            return
        end = len(pixels) // 2 if mode in ("short", "drop_data") else len(pixels)
        for at in range(0, end, BLOCK):
            block = pixels[at : min(at + BLOCK, end)].tobytes()
            try:
                conn.sendall(wire.message("ScData", "IIIIb", [frame_id, 0, at, 8, block]))
            except OSError:
                return
        if mode == "drop_data":
            close_connection(conn)
