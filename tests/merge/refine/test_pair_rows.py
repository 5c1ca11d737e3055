"""The rows of one overlap read for the heights' last solve."""

from __future__ import annotations

import numpy as np

from merge.refine.line_statistics import line_statistics
from merge.refine.pair_rows import pair_rows
from tests.merge.refine.line_mosaic import NOISE, SIDE, mosaic, pairs_of


def test_a_pair_reads_the_other_patch_where_it_lies() -> None:
    # at the true places the residuals are the two scans' line offsets and noise, nothing else
    patches, truth, _, lines = mosaic()
    rows = pair_rows(patches[0], patches[1], truth[0], truth[1])
    assert rows is not None
    assert np.all(rows.line >= 0) and np.all(rows.line < SIDE)
    expected = lines[0][rows.line] - (
        (1 - rows.f) * lines[1][rows.j] + rows.f * lines[1][rows.j + 1]
    )
    assert np.std(rows.r - expected) < 4 * NOISE
    # patches that do not meet have no rows
    assert pair_rows(patches[0], patches[8], truth[0], truth[8]) is None


def test_the_statistics_read_the_slim_rows_as_the_full_ones() -> None:
    # the sample the statistics hold drops what only the solve reads, and nothing else
    patches, truth, _, _ = mosaic()
    full = [pair_rows(patches[a], patches[b], truth[a], truth[b]) for a, b in pairs_of(patches)]
    kept = [p for p in full if p is not None]
    slim = [p.for_statistics() for p in kept]
    assert all(len(s.da) == 0 and len(s.j) == 0 for s in slim)
    assert line_statistics(slim) == line_statistics(kept)
