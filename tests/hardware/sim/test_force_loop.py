"""The simulated force loop over one line: set-point, bandwidth, slew limit, range and crash."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hardware.errors import CrashError
from hardware.sim.force_loop import Loop, _integrated, follow_line, held_error

TIP0 = 5e-6  # the tip's height with Z retracted, metres
DISTANCE = 1e-9  # the set-point's tip-sample distance
LOOP = Loop(gain=0.2, substeps=4, zrange=2e-6, branch_end=3e-9, crash_depth=-0.5e-9)


def _settled(surface: np.ndarray) -> float:
    """The extension that holds the tip at the set-point above the line's first height."""
    return float(TIP0 - surface[0] - DISTANCE)


def test_a_smooth_line_is_followed_at_the_set_point() -> None:
    x = np.linspace(0, 1, 400)
    surface = 4.9e-6 + 5e-9 * np.sin(2 * np.pi * x)
    line = follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    # the tip's height is the surface plus the set-point distance, but for the lag of a
    # first-order loop on a slope: slope per update x (1 - gain) / gain, 0.3 nm at most here
    pixels = surface.reshape(100, 4).mean(axis=1)
    np.testing.assert_allclose(line.heights, pixels + DISTANCE, rtol=0, atol=0.4e-9)
    assert line.tracking < 0.4e-9 and not line.saturated


def _ramp(rise_per_update: float) -> np.ndarray:
    """A flat line, then a ramp up over its second half."""
    surface = np.full(400, 4.9e-6)
    surface[200:] += rise_per_update * np.arange(1, 201)
    return surface


def test_a_slower_loop_lags_a_ramp_further() -> None:
    surface = _ramp(0.1e-9)
    fast = follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    slow = dataclasses.replace(LOOP, gain=0.1)
    lagging = follow_line(surface, TIP0, _settled(surface), DISTANCE, slow)
    # lags of 0.1 nm x 0.8 / 0.2 and x 0.9 / 0.1 over the ramp
    assert fast.tracking == pytest.approx(0.4e-9, rel=0.05)
    assert lagging.tracking == pytest.approx(0.9e-9, rel=0.05)


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


def test_off_the_surface_the_loop_approaches_no_faster_than_its_slew_limit() -> None:
    surface = np.full(1600, 4.9e-6)
    surface[100:] -= 50e-9  # a step down at pixel 25: the tip loses the surface
    slow = dataclasses.replace(LOOP, max_step=0.4e-9)
    line = follow_line(surface, TIP0, _settled(surface), DISTANCE, slow)
    # it acts on 0.4 nm of error at most: 0.2 x 0.4 = 0.08 nm per update, 50 nm in 625
    # updates (156 pixels); 300 updates after the step it has come 24 nm down
    assert line.heights[100] == pytest.approx(surface[0] + DISTANCE - 24e-9, abs=0.5e-9)
    np.testing.assert_allclose(line.heights[-10:], surface[-1] + DISTANCE, rtol=0, atol=0.1e-9)
    fast = follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    assert fast.heights[100] == pytest.approx(surface[-1] + DISTANCE, abs=0.1e-9)


def test_z_at_the_end_of_its_range_is_saturated() -> None:
    surface = np.full(400, 4.9e-6)
    short = dataclasses.replace(LOOP, zrange=_settled(surface) + 5e-9)
    surface[200:] -= 30e-9  # the loop would extend 30 nm more than it can
    assert follow_line(surface, TIP0, _settled(surface), DISTANCE, short).saturated


def test_a_ramp_too_steep_for_the_loop_crashes_the_tip() -> None:
    surface = _ramp(0.5e-9)  # a lag of 0.5 nm x 0.8 / 0.2 = 2 nm: 1 nm into the surface
    with pytest.raises(CrashError, match="lower the line rate"):
        follow_line(surface, TIP0, _settled(surface), DISTANCE, LOOP)
    faster = dataclasses.replace(LOOP, gain=0.5)  # 0.5 nm of lag: still above it
    assert follow_line(surface, TIP0, _settled(surface), DISTANCE, faster).heights.size == 100


def test_a_line_must_hold_whole_pixels() -> None:
    with pytest.raises(ValueError, match="whole number of pixels"):
        follow_line(np.zeros(401), TIP0, 0.0, DISTANCE, LOOP)


def test_the_held_error_is_what_a_quarter_of_the_updates_reach() -> None:
    assert held_error(np.r_[np.zeros(80), np.full(20, 3e-9)]) == 0.0  # a brief lag
    assert held_error(-np.r_[np.zeros(70), np.full(30, 3e-9)]) == pytest.approx(3e-9)
