"""Sub-cell reconstruction of kinked heights: exact on straight pieces, silent on smooth ones."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.core.kinks import (
    DRAWING,
    RINGING,
    SPLINE,
    WINDOW,
    kink_cells,
    kink_threshold,
    subcell_1d,
    subcell_2d,
)

PIXELS = np.arange(WINDOW) - (WINDOW // 2 - 1)  # -4 .. 5 about the cell [0, 1]


def _kinked(x: np.ndarray, at: float, left: float, right: float) -> np.ndarray:
    """Two straight pieces of slopes ``left`` and ``right`` meeting at ``at`` (height 0)."""
    out: np.ndarray = np.where(x < at, left * (x - at), right * (x - at))
    return out


@settings(max_examples=200, deadline=None)
@given(
    at=st.floats(-1.5, 2.5),
    left=st.floats(-5, 5),
    right=st.floats(-5, 5),
    t=st.floats(0, 1),
)
def test_one_kink_anywhere_is_reconstructed_exactly(
    at: float, left: float, right: float, t: float
) -> None:
    # wherever the kink falls, in the cell, on a pixel or beside it: the two pieces themselves
    # (a kink further out leaves the cell's cubic on one straight piece, exact too); one that
    # turns by less than the significance (20 spreads) is left to the cubic
    values = _kinked(PIXELS.astype(float), at, left, right)[None, :]
    out, kinked = subcell_1d(values, np.array([t]), np.array([1e-3]))
    error = abs(out[0] - _kinked(np.array(t), at, left, right))
    turn = abs(left - right)
    assert error <= (1e-9 if kinked[0] or turn > 0.021 else 0.25 * turn + 1e-9)


def test_a_straight_kinked_edge_at_any_angle_is_exact_in_two_dimensions() -> None:
    rng = np.random.default_rng(0)
    m = 500
    angle = rng.uniform(0, 2 * np.pi, m)
    normal = np.column_stack([np.cos(angle), np.sin(angle)])
    offset = rng.uniform(-1, 2, m)
    rows, cols = np.meshgrid(PIXELS, PIXELS, indexing="ij")

    def surface(v: np.ndarray, u: np.ndarray) -> np.ndarray:
        s = v * normal[:, 1].reshape(-1, *([1] * (v.ndim - 1)))
        s = s + u * normal[:, 0].reshape(-1, *([1] * (u.ndim - 1)))
        s = s - offset.reshape(-1, *([1] * (v.ndim - 1)))
        out: np.ndarray = 3.0 * np.maximum(s, 0.0)
        return out

    window = surface(
        np.broadcast_to(rows, (m, WINDOW, WINDOW)), np.broadcast_to(cols, (m, WINDOW, WINDOW))
    )
    fv, fu = rng.uniform(0, 1, m), rng.uniform(0, 1, m)
    out, kinked = subcell_2d(window, fv, fu, np.full(m, 1e-3))
    near = kinked  # windows the edge crosses
    assert near.mean() > 0.5
    assert np.abs(out - surface(fv, fu))[near].max() < 1e-9


def test_a_smooth_edge_is_left_to_the_spline() -> None:
    # a tanh ramp 7.5 px wide: its second differences spread over many pixels, none alone
    x = np.arange(-40, 40, dtype=float) + 0.37
    heights = 30.0 * np.tanh(x / 3.75)
    windows = np.lib.stride_tricks.sliding_window_view(heights, WINDOW)
    _, kinked = subcell_1d(windows, np.full(len(windows), 0.5), np.full(len(windows), 1e-3))
    assert not kinked.any()


def test_a_step_within_a_pixel_is_not_taken_for_one_kink() -> None:
    # flat, one pixel on the flank, flat: the line turns both ways within two pixels, which two
    # straight pieces cannot draw (the kink's place would be a guess)
    values = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 40.0, 100.0, 100.0, 100.0, 100.0]])
    _, kinked = subcell_1d(values, np.array([0.5]), np.array([1e-3]))
    assert not kinked[0]


def test_noise_below_the_threshold_leaves_the_spline() -> None:
    rng = np.random.default_rng(1)
    heights = rng.normal(0.0, 1.0, (64, 64))
    threshold = kink_threshold(heights)
    # white noise: a second difference spreads by sqrt(6) of the noise
    assert threshold == pytest.approx(np.sqrt(6.0), rel=0.1)
    assert (kink_cells(heights, threshold) & DRAWING != SPLINE).mean() < 0.01


def test_the_cells_around_a_kink_are_the_ones_flagged() -> None:
    x = np.arange(48, dtype=float)
    heights = np.tile(_kinked(x, 20.3, 0.0, 4.0), (12, 1))
    cells = kink_cells(heights, kink_threshold(heights) + 1e-3) & DRAWING != SPLINE
    flagged = np.flatnonzero(cells[5])
    # the windows that see the kink's second differences (pixels 20 and 21), and the spline's
    # ringing beyond them; nothing far from it
    assert 20 in flagged
    assert np.all(np.diff(flagged) == 1)
    assert flagged.min() >= 20 - 3 - RINGING and flagged.max() <= 21 + 2 + RINGING
    assert flagged.min() > 5 and flagged.max() < 35


def test_bad_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="values must be"):
        subcell_1d(np.zeros((3, 4)), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="window must be"):
        subcell_2d(np.zeros((3, 6, 6)), np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="2-D"):
        kink_threshold(np.zeros(5))
