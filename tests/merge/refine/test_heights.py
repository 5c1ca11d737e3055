"""The heights' last solve: Z offsets, drift planes and every scan line's offset at once."""

from __future__ import annotations

import numpy as np
import pytest

from merge.core.patchset import Patch
from merge.refine.heights import solve_heights
from merge.refine.line_statistics import LineStatistics
from tests.merge.refine.line_mosaic import (
    NOISE,
    SIDE,
    TAU,
    disturbed,
    height_errors,
    mosaic,
    pairs_of,
)


def test_the_heights_and_the_lines_offsets_are_recovered() -> None:
    patches, truth, _, lines = mosaic()
    start = disturbed(truth)
    before = height_errors(patches, start, truth)
    solved = solve_heights(patches, start, pairs_of(patches), plane_sigma=(2e-9, 2e-9))
    assert solved is not None
    after = height_errors(patches, solved.transforms, truth)
    # from over a nanometre to a fifth of one (the lines leave every patch a ramp's doubt)
    assert np.sqrt(np.mean(before**2)) > 1e-9
    assert np.sqrt(np.mean(after**2)) < 0.25 * np.sqrt(np.mean(before**2))
    # the lines' sigma as drawn (0.5 nm), and the offsets themselves, each patch's ramp and
    # mean aside (a patch's Z and plane trade with them)
    assert solved.statistics.tau == pytest.approx(TAU, rel=0.25)
    y = np.arange(SIDE) - 0.5 * (SIDE - 1)
    X = np.column_stack([np.ones(SIDE), y])

    def detrended(c: np.ndarray) -> np.ndarray:
        return c - X @ np.linalg.lstsq(X, c, rcond=None)[0]

    found = np.concatenate([detrended(c) for c in solved.line_offsets])
    drawn = np.concatenate([detrended(c) for c in lines])
    assert np.corrcoef(found, drawn)[0, 1] > 0.75


def test_known_statistics_solve_where_measured_ones_would_not() -> None:
    # lines' offsets below their means' noise: measured, the solve stands aside; told them
    # (a simulator's own, every row weighed alike), it solves, and as well as it can
    patches, truth, _, _ = mosaic(tau=0.05e-9)
    start = disturbed(truth)
    pairs = pairs_of(patches)
    assert solve_heights(patches, start, pairs, plane_sigma=(2e-9, 2e-9)) is None
    known = LineStatistics(np.inf, NOISE, 0.05e-9, 0.0)
    solved = solve_heights(patches, start, pairs, plane_sigma=(2e-9, 2e-9), statistics=known)
    assert solved is not None and solved.statistics is known
    before = height_errors(patches, start, truth)
    after = height_errors(patches, solved.transforms, truth)
    assert np.sqrt(np.mean(after**2)) < 0.25 * np.sqrt(np.mean(before**2))


@pytest.mark.parametrize("tau", [0.0, 0.01e-9])
def test_scans_whose_lines_offsets_do_not_stand_out_are_left_as_they_are(tau: float) -> None:
    # none at all, or less than the noise of a line's mean over the overlap: the refinement's
    # random effects told as much
    patches, truth, _, _ = mosaic(tau=tau)
    start = disturbed(truth)
    assert solve_heights(patches, start, pairs_of(patches), plane_sigma=(2e-9, 2e-9)) is None


def test_bad_input_is_refused() -> None:
    patches, truth, _, _ = mosaic()
    pairs = pairs_of(patches)
    with pytest.raises(ValueError, match="one transform per patch"):
        solve_heights(patches, truth[:-1], pairs, plane_sigma=(1e-9, 1e-9))
    with pytest.raises(ValueError, match="plane_sigma"):
        solve_heights(patches, truth, pairs, plane_sigma=(0.0, 1e-9))
    assert (
        solve_heights(patches, truth, np.empty((0, 2), dtype=np.intp), plane_sigma=(1e-9, 1e-9))
        is None
    )


def test_the_refinement_of_a_whole_mosaic_ends_with_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # refine() hands the whole mosaic's placement to the heights' solve and returns its
    # transforms; with patches held (a live merge's neighbourhood) it does not run
    from merge.refine import icp

    patches, truth, _, _ = mosaic()
    calls: list[int] = []

    def spy(*args: object, **kwargs: object) -> object:
        out = solve_heights(*args, **kwargs)  # type: ignore[arg-type]
        calls.append(1)
        return out

    monkeypatch.setattr(icp, "solve_heights", spy)
    pairs = pairs_of(patches)
    result = icp.refine(patches, pairs, disturbed(truth))
    assert calls == [1]
    assert np.sqrt(np.mean(height_errors(patches, result.transforms, truth) ** 2)) < 0.3e-9
    held = np.zeros(len(patches), dtype=bool)
    held[0] = True
    icp.refine(patches, pairs, disturbed(truth), held=held)
    assert calls == [1]


def test_noise_free_scans_and_missing_pixels_are_handled() -> None:
    # nothing to weigh the rows by without noise: left as they are, not divided by zero
    patches, truth, _, _ = mosaic()
    clean = [Patch(p.id, np.zeros_like(p.heights), p.origin, p.pixel_size) for p in patches]
    assert solve_heights(clean, truth, pairs_of(clean), plane_sigma=(2e-9, 2e-9)) is None
    # a scan with missing pixels (NaN) is read where it was measured
    holed = [Patch(p.id, p.heights.copy(), p.origin, p.pixel_size) for p in patches]
    for p in holed:
        p.heights[10:20, 5:40] = np.nan
    solved = solve_heights(holed, disturbed(truth), pairs_of(holed), plane_sigma=(2e-9, 2e-9))
    assert solved is not None
    assert all(np.all(np.isfinite(T.t)) and np.all(np.isfinite(T.slope)) for T in solved.transforms)
