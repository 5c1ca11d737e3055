import numpy as np
import pytest
from scipy import ndimage

from merge.start.ncc import masked_ncc
from merge.start.placement import PairMap, place_patch, pooled_maps


def _map(
    size: int,
    peaks: dict[tuple[int, int], tuple[float, float]],
    base: tuple[float, float] = (0.0, 0.0),
) -> PairMap:
    """A (2 size + 1)² map, zero shift in the centre: background NCC and count ``base``,
    ``peaks`` {shift: (ncc, count)}; the patch is the pair's first image, at rest at zero."""
    ncc = np.full((2 * size + 1, 2 * size + 1), base[0])
    count = np.full_like(ncc, base[1])
    for (dy, dx), (r, n) in peaks.items():
        ncc[dy + size, dx + size], count[dy + size, dx + size] = r, n
    return PairMap(ncc=ncc, count=count, zero=(size, size), at_rest=(0, 0), sign=1, min_overlap=16)


def test_a_high_chance_score_on_a_small_overlap_loses_to_a_good_score_on_a_large_one() -> None:
    # the true displacement: NCC 0.9 over 400 cells; a chance one: 0.97 over 30 cells (the mean
    # NCC would take it). Below half the largest overlap, the evidence counts by sqrt(cells):
    # atanh(0.97) sqrt(30 / 200) = 0.81 against atanh(0.9) = 1.47
    maps = [_map(8, {(3, -2): (0.9, 400.0)}), _map(8, {(-5, 5): (0.97, 30.0)})]
    assert place_patch(maps, radius=8) == (3, -2)
    # over as large an overlap, the better score wins: the rule is about evidence
    maps = [_map(8, {(3, -2): (0.9, 400.0)}), _map(8, {(-5, 5): (0.97, 300.0)})]
    assert place_patch(maps, radius=8) == (-5, 5)


def test_of_alike_peaks_a_period_apart_the_nearest_to_the_patch_wins() -> None:
    # a periodic sample: two peaks as good, 6 cells apart, the farther one on a larger overlap
    maps = [_map(10, {(0, 1): (0.95, 300.0), (0, 7): (0.96, 500.0)}, (0.2, 300.0))]
    assert place_patch(maps, centre=(0.0, 2.0), radius=8, ambiguity=0.1) == (0, 1)
    assert place_patch(maps, centre=(0.0, 6.0), radius=8, ambiguity=0.1) == (0, 7)


def test_pairs_agreeing_on_one_displacement_outvote_a_pair_that_does_not() -> None:
    background = (0.1, 200.0)
    maps = [
        _map(8, {(2, 1): (0.8, 200.0), (-4, 6): (0.95, 200.0)}, background),
        _map(8, {(2, 1): (0.85, 200.0)}, background),
        _map(8, {(2, 1): (0.8, 200.0)}, background),
    ]
    assert place_patch(maps, radius=8) == (2, 1)


def test_a_pair_counts_only_where_it_overlaps_enough() -> None:
    maps = [_map(8, {(1, 1): (0.99, 15.0)}), _map(8, {(-2, 0): (0.6, 40.0)})]
    assert place_patch(maps, radius=8) == (-2, 0)
    num, cells = pooled_maps(maps, (1, 0), 8)
    assert cells[0 + 8, 1 + 8] == 0 and num[0 + 8, 1 + 8] == 0
    assert place_patch(maps, radius=8, min_score=0.7) is None  # pooled NCC 0.6 is too low


def test_the_patch_is_placed_against_neighbours_on_either_side_of_its_pairs() -> None:
    # a patch `c` and two neighbours cut from one random texture; c is displaced by (3, -2)
    # cells; one neighbour is the first image of its pair, the other the second
    rng = np.random.default_rng(4)
    world = ndimage.gaussian_filter(rng.normal(size=(120, 120)), 2.0)
    u = (3, -2)
    c = world[40 + u[0] : 80 + u[0], 40 + u[1] : 80 + u[1]]
    left = world[40:80, 10:50]  # nominally 30 columns left of c
    below = world[70:110, 40:80]  # nominally 30 rows below c
    maps = []
    # pair (left, c): c is b; nominal shift e = offs[a] - offs[b] = (0, -30)
    ncc, count, zero = masked_ncc(left, c)
    maps.append(PairMap(ncc=ncc, count=count, zero=zero, at_rest=(0, -30), sign=-1, min_overlap=16))
    # pair (c, below): c is a; e = (0 - 30, 0)
    ncc, count, zero = masked_ncc(c, below)
    maps.append(PairMap(ncc=ncc, count=count, zero=zero, at_rest=(-30, 0), sign=1, min_overlap=16))
    assert place_patch(maps, radius=6) == u


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="radius"):
        place_patch([_map(2, {})], radius=-1)
    bad = PairMap(np.zeros((3, 3)), np.zeros((3, 3)), (1, 1), (0, 0), 0, 16)
    with pytest.raises(ValueError, match="sign"):
        pooled_maps([bad], (0, 0), 1)
