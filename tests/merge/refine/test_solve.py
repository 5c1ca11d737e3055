"""The damped Gauss-Newton step: priors per axis, and patches held where they are."""

from __future__ import annotations

import numpy as np
import pytest

from merge.refine.normal_system import build_normal_system
from merge.refine.solve import Priors, solve_system
from tests.merge.refine.test_rows import four_patches


def test_the_drift_plane_prior_holds_each_axis_by_its_own_sigma() -> None:
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    system = build_normal_system(bank, bank.candidates(pairs, state.R, state.s, 1.5), state, 0.1)
    plane = np.full((4, 2), 2.0)  # every patch tilted by 2 (pixels at its radius) both ways

    def step(sigma_x: float, sigma_y: float) -> np.ndarray:
        priors = Priors(
            plane=plane,
            plane_sigma=np.array([sigma_x, sigma_y]),
            shift=np.zeros((4, 2)),
            shift_sigma=np.inf,
            spin=np.zeros(4),
            spin_sigma=np.full(4, np.inf),
        )
        out: np.ndarray = solve_system(system, priors)
        return out

    even, fast = step(1.0, 1.0), step(0.1, 1.0)
    # the relative tilts are the data's; the common one is the prior's, by its sigma per axis
    assert abs(fast[:, 4].mean() + 2.0) < abs(even[:, 4].mean() + 2.0)
    assert abs(fast[:, 4].mean() + 2.0) < 0.05
    assert fast[:, 5].mean() == pytest.approx(even[:, 5].mean(), abs=0.05)


def test_held_patches_do_not_move_and_the_others_fit_against_them() -> None:
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    system = build_normal_system(bank, bank.candidates(pairs, state.R, state.s, 1.5), state, 0.1)
    priors = Priors(
        plane=np.zeros((4, 2)),
        plane_sigma=np.full(2, np.inf),
        shift=np.zeros((4, 2)),
        shift_sigma=np.inf,
        spin=np.zeros(4),
        spin_sigma=np.full(4, np.inf),
    )
    held = np.array([True, True, True, False])
    free = solve_system(system, priors)
    step = solve_system(system, priors, held=held)
    assert np.abs(step[held]).max() < 1e-6 * np.abs(free).max()
    # patch 3 alone moves, and not as it does when the others may move too
    assert np.abs(step[3]).max() > 0.1 * np.abs(free[3]).max()
    assert not np.allclose(step[3], free[3], atol=1e-3)
