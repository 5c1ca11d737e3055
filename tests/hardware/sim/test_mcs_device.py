"""The simulated controller: protocol replies and channel physics, without sockets."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.sim.mcs_channel import ChannelParams
from hardware.sim.mcs_device import MCSDevice


def dev(**kw: object) -> MCSDevice:
    d = MCSDevice(**kw)  # type: ignore[arg-type]
    assert d.handle(":SCM0", 0.0) == ":E-1,0"
    return d


def pos(d: MCSDevice, ch: int, t: float) -> float:
    reply = d.handle(f":GP{ch}", t)
    assert reply is not None
    return int(reply.split(",")[1]) * 1e-9


@pytest.mark.parametrize(
    ("line", "reply"),
    [
        ("GNC", ":E-1,1"),  # no leading colon
        (":XYZ0", ":E-1,2"),
        (":GP", ":E-1,5"),
        (":GP0,1", ":E-1,6"),
        (":GP9", ":E-1,7"),  # no channel 9
        (":MST0,40000,100,100", ":E0,7"),
        (":MSCA0,5000,10", ":E0,7"),
        (":SCM2", ":E-1,7"),
        (":GP0,a", ":E-1,1"),
        (":GNC", ":N3"),
    ],
)
def test_bad_commands_get_the_controller_s_error_replies(line: str, reply: str) -> None:
    assert dev().handle(line, 0.0) == reply


def test_asynchronous_mode_does_not_acknowledge_moves() -> None:
    d = MCSDevice()
    assert d.handle(":MST0,10,4095,1000", 0.0) is None
    assert d.handle(":GS0", 0.0) == ":S0,1"


def test_stepping_moves_by_scattered_steps_and_takes_time() -> None:
    d = dev(params=ChannelParams(sensor_noise=0.0, lost_step_probability=0.0))
    assert d.handle(":MST0,1000,4095,1000", 0.0) == ":E0,0"
    assert d.handle(":GS0", 0.5) == ":S0,1"  # still stepping half-way
    assert d.handle(":GS0", 1.01) == ":S0,0"
    moved = pos(d, 0, 1.01)
    assert moved == pytest.approx(1000 * 100e-9, rel=0.02)  # ±10 % per step averages out
    d.handle(":MST0,-1000,4095,1000", 2.0)
    back = moved - pos(d, 0, 3.1)
    assert back == pytest.approx(0.92 * 1000 * 100e-9, rel=0.02)  # backward steps are shorter


def test_end_stop_and_soft_limit() -> None:
    d = dev(params=ChannelParams(travel=(-5e-6, 5e-6), sensor_noise=0.0))
    d.handle(":MST0,30000,4095,18500", 0.0)
    assert pos(d, 0, 10.0) == pytest.approx(5e-6, abs=1e-12)
    assert d.handle(":MPA0,9000,0", 11.0) == ":E0,142"  # beyond the mechanical travel
    d.handle(":SPL0,-1000,1000", 11.0)
    assert d.handle(":MPA0,2000,0", 11.0) == ":E0,147"
    assert d.handle(":GPL0", 11.0) == ":PL0,-1000,1000"


def test_fine_mode_range_hysteresis_and_creep() -> None:
    d = dev(params=ChannelParams(sensor_noise=0.0))
    d.handle(":MSCA0,4095,4095", 0.0)
    top = pos(d, 0, 1.0)
    assert top == pytest.approx(1.6e-6, rel=0.02)
    assert d.handle(":GVL0", 1.0) == ":VL0,4095"
    later = pos(d, 0, 100.0)
    assert later - top == pytest.approx(0.01 * 1.6e-6, rel=0.05)  # creep after the move
    d2 = dev(params=ChannelParams(sensor_noise=0.0, creep_fraction=0.0))
    d2.handle(":MSCA0,2048,4096", 0.0)
    up = pos(d2, 0, 1.0)
    d2.handle(":MSCA0,4095,4096", 1.0)
    d2.handle(":MSCA0,2048,4096", 2.0)
    down = pos(d2, 0, 3.0)
    assert down - up == pytest.approx(0.015 * 1.6e-6, rel=0.05)  # the two branches differ


def test_closed_loop_reaches_the_target_within_sensor_noise() -> None:
    d = dev()
    assert d.handle(":MPA1,123456,50", 0.0) == ":E1,0"
    assert d.handle(":GS1", 0.0) == ":S1,4"
    done = d.busy_until(0.0)
    assert d.handle(":GS1", done - 0.01) == ":S1,3"  # holding
    readings = [pos(d, 1, done + 0.001) for _ in range(200)]
    assert np.mean(readings) == pytest.approx(123456e-9, abs=0.5e-9)
    assert np.std(readings) == pytest.approx(1e-9, rel=0.2)


def test_no_sensor_and_stop_and_watchdog() -> None:
    d = dev(params=ChannelParams(has_sensor=False))
    assert d.handle(":MPA0,0,0", 0.0) == ":E0,129"
    assert d.handle(":GP0", 0.0) == ":E0,129"
    d = dev()
    d.handle(":MST0,10000,4095,1000", 0.0)
    d.handle(":S0", 1.0)
    assert d.handle(":GS0", 1.0) == ":S0,0"
    d.handle(":K100", 2.0)
    d.handle(":MST0,10000,4095,1000", 2.0)
    assert d.handle(":GS0", 2.05) == ":S0,1"
    assert d.handle(":GS0", 2.5) == ":S0,0"  # 450 ms of silence: the watchdog stopped it
