import numpy as np
import pytest

from merge.start import hypotheses
from merge.start.hypotheses import split_votes
from merge.start.network import solve_pair_differences
from merge.start.trust import DOUBT

CELL = 10e-9


def _gauged(x: np.ndarray) -> np.ndarray:
    return x - x.mean(axis=0)


def _two_blocks(slip: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two columns of three patches ({0, 1, 2} and {3, 4, 5}), each tied within by sure
    pairs; of the three pairs across, two say the right column lies ``slip`` (metres, along x)
    off where the third, the right one, puts it (a corner pair slid along an edge and a side
    pair measured near where it predicted). Returns the true offsets, pairs, measurements and
    weights."""
    x = np.array([[0.0, y] for y in (0.0, 5e-7, 1e-6)] + [[5e-7, y] for y in (0.0, 5e-7, 1e-6)])
    x += np.random.default_rng(1).normal(0.0, 30e-9, x.shape)
    pairs = np.array([[0, 1], [1, 2], [3, 4], [4, 5], [0, 3], [1, 4], [1, 5]])
    m = x[pairs[:, 0]] - x[pairs[:, 1]]
    m[5:] -= [slip, 0.0]  # as if 3, 4 and 5 lay `slip` further along x
    W = np.repeat(np.eye(2)[None] / (2e-9) ** 2, len(pairs), axis=0)
    W[:4] *= 25.0  # the columns' own pairs, a nanometre's fifth
    return x, pairs, m, W


def test_an_honoured_pair_holds_and_those_against_it_are_weighed_down() -> None:
    x, pairs, m, W = _two_blocks(150e-9)
    plain = solve_pair_differences(6, pairs, m, W)
    assert plain.robust[4] < DOUBT  # outvoted two to one
    honoured = solve_pair_differences(6, pairs, m, W, honoured=4)
    np.testing.assert_allclose(_gauged(honoured.x), _gauged(x), atol=1e-10)
    assert (honoured.robust[5:] < DOUBT).all()
    with pytest.raises(ValueError, match="honoured"):
        solve_pair_differences(6, pairs, m, W, honoured=7)


def test_a_split_vote_offers_the_placement_the_doubted_pair_makes() -> None:
    x, pairs, m, W = _two_blocks(150e-9)
    base = solve_pair_differences(6, pairs, m, W)
    assert np.abs(_gauged(base.x) - _gauged(x)).max() > 70e-9  # the majority's placement
    others = split_votes(6, pairs, m, W, base, cell=CELL)
    assert [h.pair for h in others] == [4]  # the pair that measured the truth, taken for right
    np.testing.assert_allclose(_gauged(others[0].solution.x), _gauged(x), atol=1e-10)


def test_a_slip_within_a_cell_is_the_same_placement() -> None:
    _, pairs, m, W = _two_blocks(0.5 * CELL)
    base = solve_pair_differences(6, pairs, m, W)
    assert split_votes(6, pairs, m, W, base, cell=CELL) == []


@pytest.mark.parametrize(
    ("side", "wrong", "offered"),
    [
        (5, (6, 7), 0),  # a side pair inside: the loops through it all disagree with it
        (5, (3, 4), 0),  # a corner patch's, two pairs against one: one patch of 25 moves
        (3, (1, 2), 1),  # the same in a 3 x 3: one patch of 9, for the misfit to judge
    ],
)
def test_what_a_wrong_pair_of_a_grid_offers(
    side: int, wrong: tuple[int, int], offered: int
) -> None:
    # side x side patches with side and corner pairs, one pair 150 nm off
    yy, xx = np.mgrid[0:side, 0:side]
    grid = np.c_[xx.ravel(), yy.ravel()] * 500e-9
    x = grid + np.random.default_rng(2).normal(0.0, 30e-9, grid.shape)
    n = side * side
    pairs = np.array(
        [
            (a, b)
            for a in range(n)
            for b in range(a + 1, n)
            if max(abs(xx.flat[a] - xx.flat[b]), abs(yy.flat[a] - yy.flat[b])) == 1
        ]
    )
    m = x[pairs[:, 0]] - x[pairs[:, 1]]
    j = int(np.flatnonzero((pairs == wrong).all(axis=1))[0])
    m[j] += [150e-9, 0.0]
    W = np.repeat(np.eye(2)[None] / (2e-9) ** 2, len(pairs), axis=0)
    base = solve_pair_differences(n, pairs, m, W)
    assert base.robust[j] < DOUBT
    np.testing.assert_allclose(_gauged(base.x), _gauged(x), atol=1e-10)
    assert len(split_votes(n, pairs, m, W, base, cell=CELL)) == offered


def test_split_votes_wants_a_cell() -> None:
    _, pairs, m, W = _two_blocks(150e-9)
    base = solve_pair_differences(6, pairs, m, W)
    with pytest.raises(ValueError, match="cell"):
        split_votes(6, pairs, m, W, base, cell=0.0)


def test_a_repeat_of_a_lone_link_is_offered() -> None:
    # a chain 0 - 1 - 2: the link to 2, alone, took the peak nearest where the stage put it,
    # 150 nm along x from the one as likely that the truth is; nothing votes against it
    x = np.array([[0.0, 0.0], [500e-9, 0.0], [1e-6, 0.0]])
    x += np.random.default_rng(3).normal(0.0, 30e-9, x.shape)
    pairs = np.array([[0, 1], [1, 2]])
    m = x[pairs[:, 0]] - x[pairs[:, 1]]
    m[1] += [150e-9, 0.0]
    W = np.repeat(np.eye(2)[None] / (2e-9) ** 2, 2, axis=0)
    base = solve_pair_differences(3, pairs, m, W)
    assert split_votes(3, pairs, m, W, base, cell=CELL) == []  # no vote split
    found = split_votes(3, pairs, m, W, base, cell=CELL, repeats={1: ((0, -15), (2, 9))})
    assert [h.pair for h in found] == [1, 1]
    np.testing.assert_allclose(found[0].measured, x[1] - x[2], atol=1e-15)
    np.testing.assert_allclose(_gauged(found[0].solution.x), _gauged(x), atol=1e-10)


def test_a_large_mosaic_is_offered_no_alternative(monkeypatch: pytest.MonkeyPatch) -> None:
    _, pairs, m, W = _two_blocks(150e-9)
    base = solve_pair_differences(6, pairs, m, W)
    monkeypatch.setattr(hypotheses, "LARGEST", 5)
    assert split_votes(6, pairs, m, W, base, cell=CELL) == []
