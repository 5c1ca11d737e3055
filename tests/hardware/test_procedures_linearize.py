"""Rows resampled from where the Y sensor read them to an even pitch."""

from __future__ import annotations

import numpy as np

from hardware.procedures import linearize_rows


def test_bent_rows_are_put_back_on_an_even_pitch() -> None:
    ny, dy = 60, 20e-9
    index = np.arange(ny, dtype=np.float64)
    true_y = index * dy + 8e-9 * 4 * (index / ny) * (1 - index / ny)  # a hysteresis-like bow
    surface = np.sin(true_y / 150e-9)  # a feature along y, sampled at the bent rows
    heights = np.repeat(surface[:, None], 4, axis=1)
    rng = np.random.default_rng(0)
    readings = 1e-3 + true_y + rng.normal(0, 1e-9, ny)  # sensor: offset and 1 nm noise
    out = linearize_rows(heights, readings, dy)
    expected = np.sin(index * dy / 150e-9)
    before = np.abs(heights[:, 0] - expected)[2:-2].max()
    after = np.abs(out[:, 0] - expected)[2:-2].max()
    assert after < 0.2 * before


def test_without_readings_or_with_nonsense_the_rows_stay() -> None:
    heights = np.arange(40.0).reshape(20, 2)
    assert linearize_rows(heights, np.full(20, np.nan), 1e-8) is heights
    backwards = -np.arange(20.0) * 1e-8
    assert linearize_rows(heights, backwards, 1e-8) is heights
