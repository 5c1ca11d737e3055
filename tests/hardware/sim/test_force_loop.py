"""The simulated force loop over one line: a first-order loop in time (bandwidth, not pixels),
its lag on a ramp, the slew limit, the range and the crash."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hardware.errors import CrashError
from hardware.sim.force_loop import Loop, _integrated, follow_line, held_error

TIP0 = 5e-6  # the tip's height with Z retracted, metres
DISTANCE = 1e-9  # the set-point's tip-sample distance
BASE = 4e-6  # the surface's height (lab): the loop settles 1 µm into its 2 µm range
#: 1 kHz, knots 10 µs apart, 4 knots a pixel
LOOP = Loop(
    bandwidth=1000.0,
    knot_time=1e-5,
    substeps=4,
    zrange=2e-6,
    branch_end=3e-9,
    crash_depth=-0.5e-9,
)


def _settled(surface: np.ndarray) -> float:
    """The extension that holds the tip at the set-point above the line's first height."""
    return float(TIP0 - surface[0] - DISTANCE)


def _ramp(rise_per_knot: float, n: int = 4000) -> np.ndarray:
    """A flat line, then a ramp up over its second half."""
    surface = np.full(n, BASE)
    surface[n // 2 :] += rise_per_knot * np.arange(1, n - n // 2 + 1)
    return surface


def test_a_smooth_line_is_followed_at_the_set_point() -> None:
    x = np.linspace(0, 1, 400)
    surface = 4.9e-6 + 5e-9 * np.sin(2 * np.pi * x)
    line = follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    # the lag on the steepest part: 5 nm x 2π / 4 ms x 1 / (2π x 1 kHz) = 1.25 nm... over
    # 400 knots of 10 µs the line lasts 4 ms: slope x speed = 7.9 µm/s, lag 1.25 nm
    pixels = surface.reshape(100, 4).mean(axis=1)
    np.testing.assert_allclose(line.heights, pixels + DISTANCE, rtol=0, atol=1.4e-9)
    assert not line.saturated


@pytest.mark.parametrize("rate", [1e-6, 3e-6, 6e-6])  # metres per second of rise
def test_on_a_ramp_the_loop_lags_rate_over_two_pi_f_whatever_the_knots(rate: float) -> None:
    lags = []
    for knots_per_ms in (20, 100, 500):  # the same ramp in time, sampled 25 x apart
        loop = dataclasses.replace(LOOP, knot_time=1e-3 / knots_per_ms)
        n = 10 * knots_per_ms  # 10 ms
        surface = _ramp(rate * loop.knot_time, n)
        lags.append(follow_line(surface, TIP0, _settled(surface), DISTANCE, loop))
    expected = rate / (2 * math.pi * LOOP.bandwidth)
    for line in lags:
        # a steady ramp for 5 ms (31 time constants): the error it held is the lag
        assert line.tracking == pytest.approx(expected, rel=0.05)


def test_the_whole_line_filter_equals_the_loop_updated_one_by_one() -> None:
    # on the repulsive branch, within range and the slew limit, the two paths are one loop
    rng = np.random.default_rng(1)
    surface = 4.9e-6 + np.cumsum(rng.normal(0, 0.05e-9, 800))
    ext = _settled(surface)
    whole = follow_line(surface, TIP0, ext, DISTANCE, LOOP)
    stepped = _integrated(surface, TIP0, ext, DISTANCE, LOOP, 200)
    np.testing.assert_allclose(whole.heights, stepped.heights, rtol=0, atol=1e-15)
    assert whole.extension == pytest.approx(stepped.extension, abs=1e-15)
    assert whole.tracking == pytest.approx(stepped.tracking, abs=1e-15)


def test_off_the_surface_the_loop_approaches_no_faster_than_its_slew_rate() -> None:
    surface = np.full(1600, 4.9e-6)
    surface[100:] -= 50e-9  # a step down: the tip loses the surface
    slow = dataclasses.replace(LOOP, slew_rate=1e-6)  # 1 µm/s: 10 pm a knot
    line = follow_line(surface, TIP0, _settled(surface), DISTANCE, slow)
    # 50 nm at 10 pm a knot take 5000 knots: 300 knots after the step it came 3 nm down
    assert line.heights[100] == pytest.approx(surface[0] + DISTANCE - 3e-9, abs=0.2e-9)
    fast = follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)  # 40 µm/s
    np.testing.assert_allclose(fast.heights[-10:], surface[-1] + DISTANCE, rtol=0, atol=0.1e-9)


def test_z_at_the_end_of_its_range_is_saturated() -> None:
    surface = np.full(400, 4.9e-6)
    short = dataclasses.replace(LOOP, zrange=_settled(surface) + 5e-9)
    surface[200:] -= 30e-9  # the loop would extend 30 nm more than it can
    assert follow_line(surface, TIP0, _settled(surface), DISTANCE, short).saturated


def test_a_surface_rising_faster_than_the_loop_follows_crashes_the_tip() -> None:
    # 1.5 nm of clearance to the crash depth; a rise of 20 µm/s lags 3.2 nm at 1 kHz
    surface = _ramp(20e-6 * LOOP.knot_time)
    with pytest.raises(CrashError, match="lower the line rate"):
        follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    faster = dataclasses.replace(LOOP, bandwidth=3000.0)  # 1.1 nm of lag: above it
    assert follow_line(surface, TIP0, _settled(surface), DISTANCE, faster).heights.size == 1000


def test_a_slow_line_follows_a_steep_ramp_that_a_fast_one_crashes_on() -> None:
    surface = _ramp(20e-6 * LOOP.knot_time)
    slow = dataclasses.replace(LOOP, knot_time=LOOP.knot_time * 10)  # the same ramp, 10 x slower
    assert follow_line(surface, TIP0, _settled(surface), DISTANCE, slow).tracking < 0.4e-9


def test_a_retracted_z_meeting_a_rising_surface_is_a_crash_at_its_limit() -> None:
    surface = _ramp(1e-11, 40000) + 0.9e-6  # 1 µm/s, 200 nm up; Z 100 nm from retracted
    with pytest.raises(CrashError, match="fully retracted"):
        follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)


def test_a_line_must_hold_whole_pixels() -> None:
    with pytest.raises(ValueError, match="whole number of pixels"):
        follow_line(np.zeros(401), TIP0, 0.0, DISTANCE, LOOP)


def test_the_held_error_is_what_a_quarter_of_the_updates_reach() -> None:
    assert held_error(np.r_[np.zeros(80), np.full(20, 3e-9)]) == 0.0  # a brief lag
    assert held_error(-np.r_[np.zeros(70), np.full(30, 3e-9)]) == pytest.approx(3e-9)
