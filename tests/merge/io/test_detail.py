"""Levels of detail: block means that fit a budget, read a band of rows at a time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.io import detail
from merge.io.detail import block_means, detail_step


@settings(max_examples=50, deadline=None)
@given(ny=st.integers(1, 300), nx=st.integers(1, 300), budget=st.integers(1, 5000))
def test_the_step_is_the_least_that_keeps_the_budget(ny: int, nx: int, budget: int) -> None:
    k = detail_step((ny, nx), budget)
    blocks = lambda k: -(-ny // k) * -(-nx // k)  # noqa: E731
    assert blocks(k) <= budget
    assert k == 1 or blocks(k - 1) > budget


def test_block_means_ignore_holes_and_take_what_is_left_at_the_edges(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(detail, "BAND_VALUES", 3 * 11)  # bands of one block row
    h = np.arange(10 * 11, dtype=np.float64).reshape(10, 11)
    h[0, 0] = np.nan
    h[9, :] = np.nan  # the last block row holds only NaN
    out = block_means(h, 3)
    assert out.shape == (4, 4)
    assert out[0, 0] == pytest.approx(np.nanmean(h[:3, :3]))
    assert out[1, 3] == pytest.approx(h[3:6, 9:].mean())  # an edge block, 3 x 2
    assert np.isnan(out[3]).all()
    np.testing.assert_array_equal(block_means(h, 1), h)


def test_a_memory_mapped_mosaic_gives_the_means_of_the_array(tmp_path: Path) -> None:
    h = np.random.default_rng(0).normal(size=(1000, 700))
    np.save(tmp_path / "m.npy", h)
    mapped = np.load(tmp_path / "m.npy", mmap_mode="r")
    k = detail_step(mapped.shape, 20_000)
    out = block_means(mapped, k)
    assert out.size <= 20_000
    np.testing.assert_allclose(
        out[:-1, :-1],
        h[: (len(out) - 1) * k, : (out.shape[1] - 1) * k]
        .reshape(len(out) - 1, k, out.shape[1] - 1, k)
        .mean(axis=(1, 3)),
        rtol=1e-12,
    )


def test_bad_requests_are_value_errors() -> None:
    with pytest.raises(ValueError, match="budget"):
        detail_step((10, 10), 0)
    with pytest.raises(ValueError, match="1 x 1"):
        block_means(np.zeros((4, 4)), 0)
    with pytest.raises(ValueError, match="2-D"):
        block_means(np.zeros(4), 2)
