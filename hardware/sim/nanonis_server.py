"""The Nanonis protocol simulator as a TCP server, with its sample stage on a second port.

One simulated world (:class:`~hardware.sim.instrument.SimulatedAFM`) answers two controllers,
each on its own wire protocol, as in the paper's robot: the Nanonis TCP interface for the PLL,
Z controller, scan generator, auto-approach and coarse motors (:attr:`NanonisServer.address`),
and the SmarAct MCS ASCII protocol for the sample stage (:attr:`NanonisServer.stage_url`).
Start it in-process for tests (``with NanonisServer(afm) as server: ...``) or as a program
(``mosaic-afm sim-nanonis``).

Faults are injected as on the MCS simulator: on the link (``drop`` the connection, stay
``silent``, answer an ``error`` block, a ``short`` response, ``garbage``), for ``count``
requests or until healed; and in the physics: ``pll_loss`` (the PLL loses the resonance) and
``z_limit`` (the sample falls away under the tip, so the Z controller runs into its limit in
the middle of a frame).
"""

from __future__ import annotations

import socketserver
from collections import deque
from typing import Literal

from hardware.nanonis import wire
from hardware.nanonis.errors import NanonisProtocolError
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_controller import NanonisController
from hardware.sim.tcp_service import TCPService, close_connection, receive_message

LinkFault = Literal["drop", "silent", "error", "short", "garbage"]
PhysicsFault = Literal["pll_loss", "z_limit"]
#: How far a ``z_limit`` fault lowers the sample: beyond the Z piezo's reach, short of a crash.
Z_LIMIT_DROP = 1.2e-6


class NanonisServer(TCPService[LinkFault]):
    """A TCP server speaking the Nanonis protocol over the world ``afm``.

    Parameters
    ----------
    afm : SimulatedAFM
        The world; its sample stage's MCS server is the stage this controller's scans see.
    host, port : str, int
        Where to listen; port 0 picks a free one (read :attr:`address`).
    """

    def __init__(self, afm: SimulatedAFM, *, host: str = "127.0.0.1", port: int = 0) -> None:
        super().__init__(host=host, port=port, code=1)
        self.afm = afm
        self.controller = NanonisController(afm)
        #: the latest commands served, for diagnosis (bounded)
        self.log: deque[str] = deque(maxlen=10_000)

    @property
    def stage_url(self) -> str:
        """The pyserial URL of the sample stage's MCS controller in the same world."""
        return self.afm.stage_server.url

    @property
    def instrument_url(self) -> str:
        """The server's ``MOSAIC_INSTRUMENT`` for this world: Nanonis and its MCS stage."""
        host, port = self.address
        return f"nanonis://{host}:{port}?stage=mcs:{self.stage_url}"

    def stop(self) -> None:
        super().stop()
        self.controller.close()

    # -- faults -----------------------------------------------------------------------------

    def inject_physics(self, fault: PhysicsFault | None, *, after_lines: int = 0) -> None:
        """A fault of the instrument itself, now or once a frame has scanned ``after_lines``
        lines (mid-frame); None heals it (PLL back, sample back) and drops pending ones."""
        afm = self.afm

        def lose_pll() -> None:
            afm.pll_lost = True

        def drop_sample() -> None:
            afm.sample_z = -Z_LIMIT_DROP

        actions = {"pll_loss": lose_pll, "z_limit": drop_sample}
        if fault is not None and fault not in actions:
            raise ValueError(f"unknown physics fault {fault!r}: use pll_loss or z_limit")
        with self.controller.world:
            if fault is None:
                afm.pll_lost, afm.sample_z = False, 0.0
                self.controller.pending.clear()
            elif after_lines > 0:
                self.controller.pending.append((actions[fault], after_lines))
            else:
                actions[fault]()

    # -- serving ----------------------------------------------------------------------------

    def serve(self, handler: socketserver.StreamRequestHandler) -> None:
        conn = handler.connection
        while True:
            got = receive_message(conn, wire.HEADER_SIZE, wire.decode_header, NanonisProtocolError)
            if got is None:
                return
            parsed, body = got
            mode = self.take_fault()
            if mode == "drop":
                close_connection(conn)
                return
            if mode == "error":
                reply = self.controller.refusal(
                    parsed.command, "simulated fault", status=self.faults.code
                )
            else:
                reply = self.controller.handle(parsed.command, body)
            self.log.append(parsed.command)
            if mode == "silent" or not parsed.respond:
                continue
            if mode == "short":
                reply = reply[: wire.HEADER_SIZE + max(0, len(reply) - wire.HEADER_SIZE) // 2]
            elif mode == "garbage":
                reply = b"\x07garbage\x00" * 5
            try:
                conn.sendall(reply)
            except OSError:
                return
            if mode == "short":  # the rest never comes: the controller went away mid-reply
                close_connection(conn)
                return
