"""The faults that spoil a patch, on its recorded heights: from the strike line on, as physics
says."""

from __future__ import annotations

import numpy as np
import pytest

from hardware.sim.faults import (
    BLUNT_TIP,
    LOST_SHARE,
    PARACHUTE_RATE,
    Z_JUMP,
    ArmedFault,
    dilate,
    parachute,
    spoil,
    strike_line,
)

PIXEL = (10e-9, 10e-9)


def _image() -> np.ndarray:
    yy, xx = np.mgrid[0:40, 0:50] * 10e-9
    return 50e-9 * np.sin(xx / 60e-9) * np.cos(yy / 80e-9)


def test_nothing_changes_before_the_strike_line() -> None:
    h = _image()
    k = strike_line(h.shape[0])
    for kind in ("tip_change", "parachute", "lost_lines", "z_jump"):
        out = spoil(h, kind, pixel_size=PIXEL)
        np.testing.assert_array_equal(out[:k], h[:k])


def test_a_z_jump_lifts_every_line_after_it_alike() -> None:
    h = _image()
    k = strike_line(h.shape[0])
    np.testing.assert_allclose(spoil(h, "z_jump", pixel_size=PIXEL)[k:] - h[k:], Z_JUMP)


def test_lost_lines_are_a_block_of_empty_lines() -> None:
    h = _image()
    out = spoil(h, "lost_lines", pixel_size=PIXEL)
    empty = np.flatnonzero(np.isnan(out).all(axis=1))
    assert len(empty) == round(LOST_SHARE * h.shape[0])
    assert np.all(np.diff(empty) == 1) and empty[0] == strike_line(h.shape[0])


def test_a_blunt_tip_never_records_below_the_surface_and_keeps_a_flat_flat() -> None:
    h = _image()
    blunt = dilate(h, BLUNT_TIP, PIXEL)
    assert np.all(blunt >= h - 1e-18)
    assert (blunt - h).max() > 5e-9  # valleys filled in
    flat = np.full((20, 20), 3e-9)
    np.testing.assert_allclose(dilate(flat, BLUNT_TIP, PIXEL), flat)


def test_a_parachuting_tip_falls_back_no_faster_than_its_rate() -> None:
    step = np.zeros((3, 30))
    step[:, :10] = 100e-9  # a step down at pixel 10
    out = parachute(step, PARACHUTE_RATE)
    assert np.all(out >= step)
    assert np.all(np.diff(out, axis=1) >= -PARACHUTE_RATE - 1e-18)
    assert out[0, 10] == pytest.approx(100e-9 - PARACHUTE_RATE)


def test_an_unknown_fault_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown fault"):
        spoil(_image(), "gremlins", pixel_size=PIXEL)


def test_an_armed_fault_acts_on_the_lines_a_spoiled_image_has_it_on() -> None:
    lines = 40
    armed = ArmedFault.arm("lost_lines", lines)
    seen = [armed.next_line() for _ in range(lines)]
    assert armed.over
    # the same lines as spoil() empties: a block from the strike line on
    lost = np.isnan(spoil(_image(), "lost_lines", pixel_size=PIXEL)).all(axis=1)
    np.testing.assert_array_equal([line_lost for _, line_lost, _ in seen], lost)
    assert [kind for kind, _, _ in seen].index("lost_lines") == strike_line(lines)
    jumps = ArmedFault.arm("z_jump", lines)
    assert [jumps.next_line()[2] for _ in range(lines)].count(True) == 1  # lifted once, for good


def test_a_fault_is_armed_only_for_a_known_kind_and_a_real_scan() -> None:
    with pytest.raises(ValueError, match="unknown fault"):
        ArmedFault.arm("gremlins", 30)
    with pytest.raises(ValueError, match="at least 2 lines"):
        ArmedFault.arm("z_jump", 1)
