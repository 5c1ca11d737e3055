"""The TESCAN SEM driver: transcript tests of what it sends and what it makes of the replies,
then the driver against the SharkSEM simulator over real sockets, faults included."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from hardware.sharksem import wire
from hardware.sharksem.client import Link, SharkSEMClient
from hardware.sharksem.errors import (
    SharkSEMError,
    SharkSEMLinkError,
    SharkSEMProtocolError,
    SharkSEMTimeout,
)
from hardware.sharksem.sem import TescanSEM
from hardware.sim.sem import SEMGeometry, SimulatedSEM
from hardware.sim.sharksem_server import SharkSEMServer
from hardware.sim.surfaces import surface_by_name


class TranscriptSocket:
    """Plays the SEM's side of one connection: each message the driver sends must be the next
    expected one, and its scripted reply (bytes, possibly none) is what it reads next. Reading
    past the script is a time-out."""

    def __init__(self, pairs: list[tuple[bytes, bytes]]) -> None:
        self.pairs = list(pairs)
        self.buffer = b""

    def sendall(self, data: bytes) -> None:
        assert self.pairs, f"unexpected message {data[:16]!r}: the transcript is over"
        expected, reply = self.pairs.pop(0)
        assert data == expected, f"sent {data!r}, expected {expected!r}"
        self.buffer += reply

    def recv(self, n: int) -> bytes:
        if not self.buffer:
            raise TimeoutError
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def shutdown(self, how: int) -> None: ...

    def close(self) -> None: ...


def ask(command: str, types: str = "", values: tuple[object, ...] = (), *, mid: int) -> bytes:
    return wire.message(command, types, list(values), message_id=mid, flags=wire.RESPOND)


def tell(command: str, types: str = "", values: tuple[object, ...] = (), *, mid: int) -> bytes:
    return wire.message(command, types, list(values), message_id=mid)


def answer(command: str, types: str, values: tuple[object, ...], *, mid: int) -> bytes:
    return wire.message(command, types, list(values), message_id=mid)


DETECTORS = "det.0.name=SE\ndet.0.detector=0\ndet.1.name=BSE\ndet.1.detector=1\n"


def _acquisition(frame: bytes, *, blocks: list[bytes]) -> tuple[TranscriptSocket, TranscriptSocket]:
    """The conversation of one 8 x 8 px acquisition of 10 µm at 2 µs a pixel on the BSE."""
    control = TranscriptSocket(
        [
            (ask("DtEnumDetectors", mid=1), answer("DtEnumDetectors", "s", (DETECTORS,), mid=1)),
            (tell("SetViewField", "f", (0.01,), mid=2), b""),
            (tell("DtSelect", "ii", (0, 1), mid=3), b""),
            (tell("DtEnable", "iii", (0, 1, 8), mid=4), b""),
            (
                ask("EnumGeometries", mid=5),
                answer(
                    "EnumGeometries",
                    "s",
                    ("geom.0.name=ImageShift\ngeom.1.name=Rotation\n",),
                    mid=5,
                ),
            ),
            (ask("GetGeometry", "i", (1,), mid=6), answer("GetGeometry", "ff", (12.5, 0.0), mid=6)),
            (
                ask("StgGetPosition", mid=7),
                answer("StgGetPosition", "fffff", (1.5, -2.0, 10.0, 0.0, 0.0), mid=7),
            ),
            (
                ask("ScScanXY", "IIIIIIIiI", (1, 8, 8, 0, 0, 7, 7, 1, 2000), mid=8),
                answer("ScScanXY", "i", (0,), mid=8),
            ),
            (tell("ScStopScan", mid=9), b""),
        ]
    )
    data = TranscriptSocket([])
    data.buffer = frame + b"".join(blocks)
    return control, data


def _data(frame: int, at: int, pixels: bytes, *, channel: int = 0) -> bytes:
    return wire.message("ScData", "IIIIb", [frame, channel, at, 8, pixels])


def _sem(control: TranscriptSocket, data: TranscriptSocket) -> TescanSEM:
    return TescanSEM(SharkSEMClient(Link(control, "control"), Link(data, "data")))  # type: ignore[arg-type]


def test_an_acquisition_is_the_sharksem_conversation_and_its_geometry() -> None:
    pixels = bytes(range(64))
    control, data = _acquisition(b"", blocks=[_data(1, 0, pixels[:40]), _data(1, 40, pixels[40:])])
    frame = _sem(control, data).acquire(field=10e-6, pixels=8, dwell=2e-6, detector="bse")
    assert not control.pairs  # every message sent, in order
    np.testing.assert_array_equal(frame.pixels, np.arange(64).reshape(8, 8))
    assert frame.pixel_size == pytest.approx(10e-6 / 8) and frame.rotation == 12.5
    assert frame.stage == pytest.approx((1.5e-3, -2e-3, 10e-3)) and frame.detector == "BSE"


@pytest.mark.parametrize(
    ("blocks", "error", "words", "stops"),
    [
        ([_data(1, 0, bytes(40))], SharkSEMTimeout, "40 of 64 px", False),  # a short frame
        ([_data(2, 0, bytes(64))], SharkSEMProtocolError, "frame 2", True),  # another's
        ([_data(1, 8, bytes(64))], SharkSEMProtocolError, "does not follow", True),  # a gap
        ([b"\x07garbled" + bytes(24)], SharkSEMProtocolError, "garbled", False),
    ],
)
def test_a_frame_that_does_not_come_whole_is_an_error_and_no_image(
    blocks: list[bytes], error: type[Exception], words: str, stops: bool
) -> None:
    control, data = _acquisition(b"", blocks=blocks)
    if not stops:  # the data link broke: the link is down, no ScStopScan goes
        control.pairs.pop()
    sem = _sem(control, data)
    with pytest.raises(error, match=words):
        sem.acquire(field=10e-6, pixels=8, dwell=2e-6, detector="BSE")
    assert not control.pairs  # the scan stopped where the control link still held
    with pytest.raises(SharkSEMLinkError, match="link is down"):  # never out of step after
        sem.version()


def test_an_unknown_detector_is_refused_naming_those_there_are() -> None:
    control = TranscriptSocket(
        [(ask("DtEnumDetectors", mid=1), answer("DtEnumDetectors", "s", (DETECTORS,), mid=1))]
    )
    with pytest.raises(SharkSEMError, match="no detector 'EBSD'; it has: SE, BSE"):
        _sem(control, TranscriptSocket([])).acquire(field=1e-5, pixels=8, detector="EBSD")


def test_a_reply_to_another_request_breaks_the_link() -> None:
    control = TranscriptSocket([(ask("TcpGetVersion", mid=1), answer("GetWD", "f", (1.0,), mid=1))])
    sem = _sem(control, TranscriptSocket([]))
    with pytest.raises(SharkSEMProtocolError, match="not to this request"):
        sem.version()
    with pytest.raises(SharkSEMLinkError, match="link is down"):
        sem.version()


# -- against the simulator, over sockets ------------------------------------------------------


@pytest.fixture
def server() -> Iterator[SharkSEMServer]:
    geometry = SEMGeometry(rotation=4.0, scale=1.03)
    sem = SimulatedSEM(surface_by_name("chessboard"), seed=3, geometry=geometry)
    with SharkSEMServer(sem) as srv:
        yield srv


def test_an_image_over_sockets_is_the_simulated_sems(server: SharkSEMServer) -> None:
    with SharkSEMClient.open(*server.address, timeout=5) as client:
        sem = TescanSEM(client)
        assert sem.version().startswith("SharkSEM")
        frame = sem.acquire(field=12e-6, pixels=128)
        slow = sem.acquire(field=12e-6, pixels=128, dwell=16e-6)
    assert frame.pixels.shape == (128, 128) and frame.pixel_size == pytest.approx(12e-6 / 128)
    assert frame.pixels.std() > 20  # a grating's edges, bright on dark
    # sixteen times the dwell: a quarter of the noise between neighbouring pixels of a flat face
    assert np.median(np.abs(np.diff(slow.pixels, axis=1))) < np.median(
        np.abs(np.diff(frame.pixels, axis=1))
    )
    assert "ScScanXY" in server.log


@pytest.mark.parametrize(
    ("fault", "error", "words"),
    [
        ("drop", SharkSEMLinkError, "closed the link"),
        ("silent", SharkSEMTimeout, "no answer"),
        ("garbage", SharkSEMProtocolError, "garbled"),
    ],
)
def test_link_faults_end_with_a_clear_error(
    server: SharkSEMServer, fault: str, error: type[Exception], words: str
) -> None:
    with SharkSEMClient.open(*server.address, timeout=1) as client:
        sem = TescanSEM(client)
        sem.version()  # the link is up and its registration served
        server.inject(fault, count=1)  # type: ignore[arg-type]
        with pytest.raises(error, match=words):
            sem.version()


@pytest.mark.parametrize(
    ("fault", "error"), [("short", SharkSEMTimeout), ("drop_data", SharkSEMLinkError)]
)
def test_a_frame_cut_short_keeps_nothing(
    server: SharkSEMServer, fault: str, error: type[Exception]
) -> None:
    with SharkSEMClient.open(*server.address, timeout=1) as client:
        sem = TescanSEM(client)
        sem.version()
        server.inject(fault, count=100)  # type: ignore[arg-type]
        start = time.monotonic()
        with pytest.raises(error):
            sem.acquire(field=12e-6, pixels=512)
        assert time.monotonic() - start < 10


def test_the_cli_serves_the_simulated_sem_and_refuses_bad_options(
    capsys: pytest.CaptureFixture[str],
) -> None:
    import subprocess
    import sys

    from backend.cli import main

    for bad in (["--port", "65535"], ["--sem-scale", "7"], ["--surface", "moon"]):
        assert main(["sim-sharksem", *bad]) == 2
        assert "error:" in capsys.readouterr().err
    proc = subprocess.Popen(
        [sys.executable, "-m", "backend.cli", "sim-sharksem", "--surface", "chessboard"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().split(" at ")[1].split()[0]  # sharksem://HOST:PORT
        host, port = url.removeprefix("sharksem://").rsplit(":", 1)
        with SharkSEMClient.open(host, int(port), timeout=5) as client:
            frame = TescanSEM(client).acquire(field=12e-6, pixels=64)
        assert frame.pixels.shape == (64, 64) and frame.pixels.std() > 10
    finally:
        proc.terminate()
        proc.wait(timeout=10)
