from __future__ import annotations

import pytest

from hardware.mcs_axis import STAGE_TRAVEL, FineCalibration, MCSAxis, TravelError
from hardware.protocols import PositionerAxis
from hardware.sim.mcs_server import MCSServer
from hardware.smaract_mcs import AxisStatus, MCSController
from tests.hardware.transcript import Transcript


def test_fine_mode_uses_the_axis_calibration_not_a_constant() -> None:
    link = Transcript([(b":MSCA0,2048,4095\n", b":E0,0\n"), (b":GVL0\n", b":VL0,2048\n")])
    axis = MCSAxis(MCSController(link), 0, name="x", calibration=FineCalibration(range=2.0e-6))
    assert isinstance(axis, PositionerAxis)
    axis.fine_to(1.0e-6, speed=2.0e-6)  # half the range, at the full range per second
    assert axis.fine_extension() == pytest.approx(2048 * 2.0e-6 / 4095)
    with pytest.raises(ValueError, match="outside"):
        axis.fine_to(2.5e-6, speed=1e-6)


def test_axis_on_the_simulator() -> None:
    with MCSServer() as srv, MCSController.open(srv.url) as ctl:
        x = MCSAxis(ctl, 0, name="x")
        x.move_to(10e-6)
        assert x.status() is AxisStatus.STOPPED
        pos = x.position()
        assert pos is not None
        assert pos == pytest.approx(10e-6, abs=5e-9)
        x.step(-100, amplitude=4095, frequency=1000)
        after = x.position()
        assert after is not None
        # 100 backward steps of 92 nm, each scattering by ±10 %
        assert pos - after == pytest.approx(100 * 92e-9, rel=0.03)
        assert MCSAxis(ctl, 1, name="blind", has_sensor=False).position() is None


def test_a_move_past_the_stage_travel_is_refused_before_anything_is_sent() -> None:
    link = Transcript([(b":MPA0,5999000,0\n", b":E0,0\n")])  # the only command that goes (nm)
    stage = MCSAxis(MCSController(link), 0, name="stage x", travel=STAGE_TRAVEL)
    stage.move_to(5.999e-3)
    for target in (6.0005e-3, -6.0005e-3, float("nan"), float("inf")):
        with pytest.raises(TravelError, match="past its travel"):
            stage.move_to(target)


def test_the_simulated_stage_stays_within_its_travel() -> None:
    with MCSServer() as srv, MCSController.open(srv.url) as ctl:
        stage = MCSAxis(ctl, 0, name="stage x", travel=STAGE_TRAVEL)
        stage.move_to(5.9e-3)
        with pytest.raises(TravelError):
            stage.move_to(6.0005e-3)
        assert stage.position() == pytest.approx(5.9e-3, abs=50e-9)
