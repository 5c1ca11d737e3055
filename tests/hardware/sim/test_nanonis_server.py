"""The simulator speaks the Nanonis wire protocol: the vendor's own client works unchanged."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import nanonis_spm
import numpy as np
import pytest

from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.surfaces import Chessboard


@pytest.fixture
def server() -> Iterator[NanonisServer]:
    with SimulatedAFM(Chessboard(seed=1), seed=1) as afm, NanonisServer(afm) as srv:
        yield srv


@pytest.fixture
def vendor(server: NanonisServer) -> Iterator[nanonis_spm.Nanonis]:
    conn = socket.create_connection(server.address, timeout=10)
    yield nanonis_spm.Nanonis(conn)
    conn.close()


def values(reply: tuple[object, ...]) -> list[object]:
    """The decoded values of a nanonis_spm reply, after checking its error text is empty."""
    error, _, decoded = reply
    assert error == "", error
    assert isinstance(decoded, list)
    return decoded


def test_the_vendor_client_lands_scans_and_grabs_a_frame(
    server: NanonisServer, vendor: nanonis_spm.Nanonis
) -> None:
    (df,) = values(vendor.PLL_FreqShiftGet(1))
    assert abs(float(df)) < 1.0  # far from the surface: no interaction
    values(vendor.ZCtrl_SetpntSet(10.0))
    assert values(vendor.ZCtrl_SetpntGet()) == [10.0]
    values(vendor.AutoApproach_OnOffSet(1))
    deadline = time.monotonic() + 30
    while values(vendor.AutoApproach_OnOffGet()) != [0]:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert values(vendor.ZCtrl_OnOffGet()) == [1]  # landed at the set-point, loop engaged
    assert float(values(vendor.PLL_FreqShiftGet(1))[0]) == pytest.approx(10.0, abs=1.0)
    (z,) = values(vendor.ZCtrl_ZPosGet())
    assert -0.8e-6 < float(z) < 0.8e-6
    values(vendor.Scan_FrameSet(0.0, 0.0, 0.8e-6, 0.6e-6, 0.0))
    assert values(vendor.Scan_FrameGet())[2:4] == pytest.approx([0.8e-6, 0.6e-6])
    values(vendor.Scan_BufferSet([14], 30, 24))  # coerced to 32 pixels, as the real one does
    assert values(vendor.Scan_BufferGet())[2:] == [32, 24]
    values(vendor.Scan_SpeedSet(0.0, 0.0, 0.5, 0.25, 2, 2.0))
    assert values(vendor.Scan_SpeedGet())[2:4] == [0.5, 0.25]
    values(vendor.Scan_Action(0, 1))
    timed_out, _, path = values(vendor.Scan_WaitEndOfScan(30_000))
    assert (timed_out, path) == (0, "")
    assert values(vendor.Scan_StatusGet()) == [0]
    _, name, rows, cols, data, up = values(vendor.Scan_FrameDataGrab(14, 1))
    assert (name, rows, cols, up) == ("Z (m)", 24, 32, 1)
    data = np.asarray(data)
    assert np.isfinite(data).all()
    # the frame is the sample under the scan range's middle (the stage stands at 0): the
    # true surface there, as the tip rides over it, up to Z's offset and the plane of the
    # thermal Z drift over the frame
    truth = server.afm.true_heights(0.4e-6 + 12.5e-9, 0.5e-6 + 12.5e-9, (24, 32), 25e-9, tip=True)
    rows, cols = np.mgrid[0:24, 0:32]
    basis = np.column_stack([np.ones(rows.size), rows.ravel(), cols.ravel()])
    diff = (data - truth).ravel()
    error = diff - basis @ np.linalg.lstsq(basis, diff, rcond=None)[0]
    assert np.median(np.abs(error)) < 3e-9 < np.ptp(truth)
    _, _, _, _, back, _ = values(vendor.Scan_FrameDataGrab(14, 0))
    assert np.median(np.abs(np.asarray(back) - data)) < 10e-9  # the same surface, both ways
    values(vendor.ZCtrl_Withdraw(1, 1000))
    assert values(vendor.ZCtrl_OnOffGet()) == [0]
    assert float(values(vendor.ZCtrl_ZPosGet())[0]) == pytest.approx(0.8e-6, abs=1e-9)
    values(vendor.ZCtrl_OnOffSet(0))


def test_an_unknown_command_gets_an_error_block_saying_so(vendor: nanonis_spm.Nanonis) -> None:
    error, _, _ = vendor.quickSend("Laser.Fire", [], [], [])
    assert "unknown command 'Laser.Fire'" in error


def test_refused_arguments_come_back_in_the_error_block(vendor: nanonis_spm.Nanonis) -> None:
    error, _, _ = vendor.Scan_FrameSet(0.0, 0.0, 5e-6, 5e-6, 0.0)
    assert "leaves the scan range" in error
    error, _, _ = vendor.Scan_Action(0, 1)
    assert "land before scanning" in error
    error, _, _ = vendor.Scan_BufferSet([3], 32, 32)
    assert "records Z only" in error


def test_the_stage_of_the_same_world_speaks_mcs(server: NanonisServer) -> None:
    from hardware.smaract_mcs import MCSController

    with MCSController.open(server.stage_url) as stage:
        stage.move_absolute(0, 2e-6)
        while stage.status(0) != 0:
            pass
        t = server.afm.clock.now()
        assert server.afm.stage_device.axes[0].true_position(t) == pytest.approx(2e-6, abs=50e-9)
    assert server.instrument_url.startswith("nanonis://127.0.0.1:")
