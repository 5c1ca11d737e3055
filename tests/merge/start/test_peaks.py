import numpy as np
import pytest

from merge.start.peaks import find_peak


def _ridge(bumps: dict[int, float], seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An NCC map with a ridge along x through dy = 0 (a straight edge) at 0.7, noise of 0.02
    along it, and bumps ``{dx: height}`` above the ridge."""
    ky = np.arange(21)[:, None] - 10
    ncc = 0.7 * np.exp(-(ky**2) / 4.0) + np.zeros((21, 41))
    ncc[10] += np.random.default_rng(seed).uniform(-0.02, 0.02, 41)
    for dx, height in bumps.items():
        kernel = np.array([[0.5, 0.7, 0.5], [0.7, 1.0, 0.7], [0.5, 0.7, 0.5]])
        ncc[9:12, 19 + dx : 22 + dx] += height * kernel
    return ncc, np.full(ncc.shape, 500.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_texture_along_an_edge_beats_the_expected_shift(seed: int) -> None:
    # a bump at the expected shift scores within the ambiguity of the best at dx = +8, but the
    # best stands out of the ridge between them by more: that is where the texture matches
    ncc, count = _ridge({0: 0.06, 8: 0.16}, seed)
    peak = find_peak(ncc, count, (10, 20), radius=(12, 12), ambiguity=0.1)
    assert peak is not None and peak.integer_shift == (0, 8)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_along_a_bare_ridge_the_expected_shift_wins(seed: int) -> None:
    # bumps of noise only (the highest at dx = +8): which of them scores highest says nothing,
    # so the bump nearest the expected shift wins (bumps lie a few cells apart)
    ncc, count = _ridge({8: 0.03}, seed)
    peak = find_peak(ncc, count, (10, 20), radius=(12, 12), ambiguity=0.1)
    assert peak is not None and peak.integer_shift[0] == 0 and abs(peak.integer_shift[1]) <= 3
    # and the peak says so: its alike neighbours lie along the ridge (x), none across it
    assert peak.ridge and all(dy == 0 and dx != 0 for dy, dx in peak.ridge)
    assert peak.repeats == ()  # no valley between them: one ridge, not a repeat


@pytest.mark.parametrize("expected", [(0.0, 0.0), (0.0, 7.0)])
def test_a_periodic_map_names_its_repeats_and_takes_the_nearest(
    expected: tuple[float, float],
) -> None:
    # a grating's map: peaks every 8 cells along x, valleys between, falling off across
    ky, kx = np.mgrid[-10:11, -20:21]
    ncc = 0.1 + 0.8 * np.cos(np.pi * kx / 8.0) ** 2 * np.exp(-(ky**2) / 4.0)
    ncc -= 0.001 * np.abs(kx)  # the one at the centre scores a little above the others
    peak = find_peak(ncc, np.full(ncc.shape, 500.0), (10, 20), expected=expected, ambiguity=0.1)
    assert peak is not None and peak.integer_shift == (0, 8 * round(expected[1] / 8))
    assert peak.ridge == ()
    # every other peak within reach of the best's score, each a multiple of 8 cells along x
    assert peak.repeats and all(dy == 0 and dx % 8 == 0 for dy, dx in peak.repeats)
    assert min(abs(dx) for _, dx in peak.repeats) == 8


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_peak_that_stands_out_of_its_ridge_has_no_alike_neighbours(seed: int) -> None:
    ncc, count = _ridge({0: 0.06, 8: 0.16}, seed)
    peak = find_peak(ncc, count, (10, 20), radius=(12, 12), ambiguity=0.1)
    assert peak is not None and peak.ridge == () and peak.repeats == ()


@pytest.mark.parametrize("pad", [(1, 0), (0, 1), (1, 1), (2, 3)])
def test_the_peak_does_not_depend_on_where_the_map_starts(pad: tuple[int, int]) -> None:
    # two alike peaks a knight's move apart: the straight path between them passes half-way
    # between two cells, one on the ridge that joins them and one in a valley
    ncc = np.full((21, 21), 0.2)
    ncc[10, 10], ncc[11, 12] = 0.8, 0.75
    ncc[10, 11], ncc[11, 11] = 0.74, 0.5
    peak = find_peak(ncc, np.full(ncc.shape, 500.0), (10, 10), ambiguity=0.1)
    assert peak is not None and peak.integer_shift == (0, 0)
    # the same map with rows and columns of lower scores before and after it
    py, px = pad
    wide = np.random.default_rng(0).uniform(-1.0, 0.1, (21 + 2 * py, 21 + 2 * px))
    wide[py : py + 21, px : px + 21] = ncc
    other = find_peak(wide, np.full(wide.shape, 500.0), (10 + py, 10 + px), ambiguity=0.1)
    assert other is not None
    assert (other.shift, other.ridge, other.score) == (peak.shift, peak.ridge, peak.score)


def test_too_little_overlap_or_an_empty_window_finds_no_peak() -> None:
    ncc = np.full((11, 11), 0.5)
    ncc[5, 5] = 0.9
    assert find_peak(ncc, np.full(ncc.shape, 10.0), (5, 5), min_overlap=16) is None
    count = np.full(ncc.shape, 100.0)
    assert find_peak(ncc, count, (5, 5), expected=(40.0, 0.0), radius=(2.0, 2.0)) is None
    peak = find_peak(ncc, count, (5, 5), radius=(2.0, 2.0))
    assert peak is not None and peak.integer_shift == (0, 0) and peak.score == 0.9
