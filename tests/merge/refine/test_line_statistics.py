"""What the overlaps' residuals say before the heights' last solve: noise, lines, weights."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.refine.line_statistics import line_statistics, line_weights
from merge.refine.pair_rows import PairRows, pair_rows
from tests.merge.refine.line_mosaic import NOISE, TAU, mosaic, pairs_of


def test_the_lines_sigma_is_measured_from_the_rows() -> None:
    patches, truth, _, _ = mosaic(seed=3)
    pairs = pairs_of(patches)
    rows = [pair_rows(patches[a], patches[b], truth[a], truth[b]) for a, b in pairs.tolist()]
    kept = [r for r in rows if r is not None]
    stats = line_statistics(kept, [(NOISE, NOISE)] * len(kept))
    assert stats.tau == pytest.approx(TAU, rel=0.25)
    assert stats.noise == pytest.approx(NOISE * np.sqrt(1.5), rel=0.3)
    # no rows, no statistics
    assert line_statistics([]).tau == 0.0


@settings(max_examples=30, deadline=None)
@given(
    shift=st.floats(-50e-9, 50e-9),
    line=st.integers(0, 9),
    seed=st.integers(0, 2**16),
)
def test_a_lines_offset_does_not_change_the_weights(shift: float, line: int, seed: int) -> None:
    # robust weights taken on the residuals themselves would shrink the lines with large
    # offsets; taken on the deviations from their line's mean, they do not see them
    rng = np.random.default_rng(seed)
    m = 200
    at = np.repeat(np.arange(10), m // 10)
    r = rng.normal(0.0, 1e-9, m)
    r[5] += 30e-9  # an outlier
    rows = PairRows(r, at, at, np.zeros(m), np.zeros((m, 2)), np.zeros((m, 2)))
    moved = PairRows(
        r + shift * (at == line), at, at, np.zeros(m), np.zeros((m, 2)), np.zeros((m, 2))
    )
    w0, w1 = line_weights(rows, 1e-9), line_weights(moved, 1e-9)
    np.testing.assert_allclose(w1, w0, rtol=1e-6, atol=1e-9)
    assert w0[5] < 0.05
