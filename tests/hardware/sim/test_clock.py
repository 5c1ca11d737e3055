"""The simulated clock: time moves on demand, a paced clock takes wall time for it, and only a
long silence passes as time by itself."""

from __future__ import annotations

import threading

import pytest

from hardware.sim.clock import IDLE, SimClock


class Wall:
    """A wall clock the test moves (and a sleep that moves it)."""

    def __init__(self) -> None:
        self.t = 100.0
        self.slept: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.t += seconds


def paced(speed: float) -> tuple[SimClock, Wall]:
    wall = Wall()
    return SimClock(speed, wall=wall, sleep=wall.sleep), wall


def test_fast_clock_stands_still_and_jumps() -> None:
    wall = Wall()
    clock = SimClock(None, wall=wall, sleep=wall.sleep)
    wall.t += 50.0
    assert clock.now() == 0.0  # no silence passes
    assert clock.advance(2.5) == 2.5
    assert clock.advance_to(1.0) == 2.5  # already later
    assert wall.slept == []


def test_paced_advance_takes_wall_time() -> None:
    clock, wall = paced(50.0)
    assert clock.advance(5.0) == pytest.approx(5.0)
    assert wall.slept == [pytest.approx(0.1)]
    assert clock.advance_to(6.0) == pytest.approx(6.0)
    assert wall.slept[-1] == pytest.approx(0.02)


def test_host_pauses_are_not_instrument_time() -> None:
    """A busy host's milliseconds between two lines are not multiplied into creep."""
    clock, wall = paced(50.0)
    t0 = clock.advance(0.5)  # a line
    wall.t += 0.8 * IDLE  # the host thinks
    assert clock.now() == pytest.approx(t0)
    wall.t += 0.8 * IDLE  # and again: each look at the clock starts the silence anew
    assert clock.now() == pytest.approx(t0)


def test_a_long_silence_passes_as_time() -> None:
    """The host gone or an operator idle: drift goes on and a watchdog trips."""
    clock, wall = paced(10.0)
    wall.t += 3 * IDLE
    assert clock.now() == pytest.approx(30 * IDLE)


def test_time_runs_during_an_advance_in_flight() -> None:
    """Another thread looking at the clock while a line is under way sees time run at the
    clock's speed, never past the line's end."""
    clock, wall = paced(10.0)
    started, release = threading.Event(), threading.Event()

    def slow_sleep(seconds: float) -> None:
        started.set()
        release.wait(5)
        wall.t += seconds

    clock._sleep = slow_sleep
    worker = threading.Thread(target=clock.advance, args=(4.0,))
    worker.start()
    assert started.wait(5)
    wall.t += 0.1
    assert clock.now() == pytest.approx(1.0)
    wall.t += 10.0
    assert clock.now() == pytest.approx(4.0)  # capped at the advance's end
    release.set()
    worker.join(5)
    assert clock.now() == pytest.approx(4.0)


def test_time_only_moves_forward() -> None:
    with pytest.raises(ValueError, match="forward"):
        SimClock(None).advance(-1.0)
    with pytest.raises(ValueError, match="positive"):
        SimClock(0.0)
