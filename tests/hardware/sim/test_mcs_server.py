"""The real driver against the protocol simulator through real socket:// URLs."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from hardware.sim.mcs_server import MCSServer
from hardware.smaract_errors import MCSControllerError, MCSLinkError, MCSProtocolError, MCSTimeout
from hardware.smaract_mcs import AxisStatus, MCSController, open_link


@pytest.fixture
def server() -> Iterator[MCSServer]:
    with MCSServer() as srv:
        yield srv


def test_driver_talks_to_the_simulator(server: MCSServer) -> None:
    with MCSController.open(server.url, timeout=1.0) as c:
        assert c.channel_count() == 3
        c.move_absolute(0, 2e-6, hold_ms=0)
        assert c.status(0) is AxisStatus.STOPPED  # fast time: the move is done when polled
        assert c.position(0) == pytest.approx(2e-6, abs=5e-9)
        c.step(1, 500, amplitude=4095, frequency=5000)
        assert c.position(1) == pytest.approx(500 * 100e-9, rel=0.05)
        c.scan_absolute(2, 4095, speed=100000)
        assert c.voltage_level(2) == 4095
        with pytest.raises(MCSControllerError) as err:
            c.step(7, 1, amplitude=1, frequency=1)
        assert err.value.code == 7
    assert server.log[0] == (":SCM0", ":E-1,0")


@pytest.mark.parametrize(
    ("fault", "error"),
    [
        ("silent", MCSTimeout),
        ("garbage", MCSProtocolError),
        ("error", MCSControllerError),
        ("drop", (MCSLinkError, MCSTimeout)),
    ],
)
def test_each_fault_gives_its_typed_error_within_the_time_out(
    server: MCSServer, fault: str, error: type[Exception] | tuple[type[Exception], ...]
) -> None:
    # Opened at the usual time-out: on a loaded machine the first reply can take over 0.3 s, and
    # the open is not what this test is about. The faults are then timed against a short one.
    link = open_link(server.url, timeout=2.0)
    with MCSController(link, name=server.url) as c:
        c.set_synchronous()
        link.timeout = 0.3  # type: ignore[attr-defined]  # pyserial's own setter
        server.inject(fault)  # type: ignore[arg-type]
        start = time.monotonic()
        with pytest.raises(error):
            c.position(0)  # a read: retried once, so at most two time-outs
        assert time.monotonic() - start < 1.5
        with pytest.raises(error):
            c.stop(0)
        server.inject(None)


def test_unreachable_controller_is_a_link_error() -> None:
    with MCSServer() as srv:
        url = srv.url
    with pytest.raises(MCSLinkError):
        MCSController.open(url, timeout=0.3)


def test_every_command_and_error_reply_through_the_socket() -> None:
    from hardware.sim.mcs_channel import ChannelParams
    from hardware.sim.mcs_device import MCSDevice
    from hardware.smaract_errors import (
        EndStopError,
        MCSCommandError,
        NoSensorError,
        RangeLimitError,
    )

    device = MCSDevice(channels=2, params=ChannelParams(travel=(-1e-3, 1e-3)))
    with MCSServer(device) as srv, MCSController.open(srv.url) as c:
        c.move_relative(0, 5e-6)
        assert c.position(0) == pytest.approx(5e-6, abs=5e-9)
        c.scan_absolute(1, 1000, speed=100000)
        assert c.status(1) is AxisStatus.STOPPED  # a relative scan starts where it stands
        c.scan_relative(1, -500, speed=100000)
        assert c.voltage_level(1) == 500
        c.step(0, 30000, amplitude=4095, frequency=100)  # 5 minutes of steps
        c.stop(0)
        assert c.status(0) is AxisStatus.STOPPED
        c.set_watchdog(0)
        c.set_position_limit(0, -2e-6, 2e-6)
        assert c.position_limit(0) == pytest.approx((-2e-6, 2e-6))
        with pytest.raises(RangeLimitError):
            c.move_absolute(0, 3e-6)
        c.set_position_limit(0, 0.0, 0.0)  # removed
        with pytest.raises(EndStopError):
            c.move_absolute(0, 5e-3)  # beyond the mechanical travel
        with pytest.raises(MCSCommandError) as err:
            c.scan_relative(1, -4000, speed=1)  # below level 0
        assert err.value.code == 7
        with pytest.raises(MCSCommandError) as err:
            c.command("XYZ0")
        assert err.value.code == 2
    blind = MCSDevice(channels=1, params=ChannelParams(has_sensor=False))
    with MCSServer(blind) as srv, MCSController.open(srv.url) as c:
        with pytest.raises(NoSensorError):
            c.position(0)
        with pytest.raises(NoSensorError):
            c.move_absolute(0, 1e-6)
