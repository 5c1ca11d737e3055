"""One level of the refinement: when its steps stop."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
import pytest

from hardware.sim.surfaces import FoldedSurface
from merge import pipeline
from merge.config import MergeConfig
from merge.refine import icp, level
from merge.refine.bank import SurfaceBank
from merge.refine.icp import DEFAULT_LEVELS
from merge.refine.level import FREEZE_MEASURED, FREEZE_MOTION, _cycled, _small
from tests.conftest import Synthetic, make_synthetic, tip_drawn_paper_grid

T = TypeVar("T")


def test_steps_that_cycle_count_as_a_stall_and_a_creep_does_not() -> None:
    step = np.zeros((3, 6))
    step[1, 0] = 0.01
    two = [(3.1213e-9, step), (3.1221e-9, -step), (3.1213e-9, step)]
    assert _cycled(two)
    turn = np.zeros((3, 6))
    turn[2, 1] = 0.01
    three = [(3.0969e-9, step), (3.0971e-9, turn), (3.0979e-9, -step - turn), (3.0969e-9, step)]
    assert _cycled(three)
    # a patch creeping along a grating's stripes moves on the same way, the cost barely falling
    creep = [(1.3783e-9, step), (1.3782e-9, step), (1.3781e-9, step), (1.3780e-9, step)]
    assert not _cycled(creep)
    assert not _cycled(two[:2])  # too short to tell


def test_the_raw_level_stops_once_steps_move_no_height_by_a_tenth_of_the_noise(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch
) -> None:
    ps = small_mosaic.patch_set
    default = pipeline.run(ps)
    monkeypatch.setattr(level, "HEIGHT_TOL", 0.0)
    polished = pipeline.run(ps)
    assert default.iterations < polished.iterations
    e_default = small_mosaic.registration_error(default.transforms)
    e_polished = small_mosaic.registration_error(polished.transforms)
    # what the extra iterations buy is far below the noise (1 nm) in either direction
    assert abs(e_default[0] - e_polished[0]) < 0.05e-9
    assert abs(e_default[1] - e_polished[1]) < 0.05e-9


def test_the_raw_level_holds_its_robust_weights_once_its_steps_are_small(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch
) -> None:
    # raw level, weights held, weights kept; and the patches the start measured
    seen = _steps_recorded(
        monkeypatch,
        lambda lv, kw: ((lv.raw, kw["weights"] is not None, kw["freeze"]), lv.measured),
    )
    # as soon as the first raw step is done
    monkeypatch.setattr(level, "FREEZE_MOTION", 1e6)
    monkeypatch.setattr(level, "FREEZE_MEASURED", 1e6)
    monkeypatch.setattr(level, "HEIGHT_TOL", 0.0)  # steps until no patch moves 1e-3 px
    pipeline.run(small_mosaic.patch_set)
    steps = [s for s, _ in seen]
    raw = [s for s in steps if s[0]]
    assert not any(held or freeze for r, held, freeze in steps if not r)
    assert len(raw) >= 3 and raw[0] == (True, False, False)
    assert raw[1] == (True, False, True)  # the weights of the second step are kept ...
    assert all(s == (True, True, False) for s in raw[2:])  # ... and held after
    # the pipeline tells the levels which patches its start measured (here all of them)
    assert all(m is not None and m.all() for _, m in seen)
    seen.clear()
    monkeypatch.setattr(level, "FREEZE_MOTION", 0.0)  # never
    monkeypatch.setattr(level, "FREEZE_MEASURED", 0.0)
    pipeline.run(small_mosaic.patch_set)
    assert seen and not any(held or freeze for (_, held, freeze), _ in seen)


def test_the_weights_are_held_sooner_where_only_patches_the_start_measured_still_move() -> None:
    tol = 1e-3
    between = 0.5 * (FREEZE_MOTION + FREEZE_MEASURED) * tol  # past one limit, within the other
    motions = np.array([0.1 * tol, between])
    assert not _small(None, None, tol)  # no step yet
    assert not _small(motions, None, tol)  # not known: as if no patch was measured
    assert not _small(motions, np.array([True, False]), tol)  # the one still moving: unmeasured
    assert _small(motions, np.array([False, True]), tol)  # ... measured: it may creep that much
    assert not _small(np.array([0.1 * tol, 2 * FREEZE_MEASURED * tol]), np.ones(2, bool), tol)


def _steps_recorded(monkeypatch: pytest.MonkeyPatch, what: Callable[[Any, Any], T]) -> list[T]:
    """What ``what(level_setup, step_kwargs)`` says of every refinement step from now on."""
    seen: list[T] = []
    step = level._step

    def recorded(fit: Any, lv: Any, cand: Any, **kwargs: Any) -> Any:
        seen.append(what(lv, kwargs))
        return step(fit, lv, cand, **kwargs)

    monkeypatch.setattr(level, "_step", recorded)
    return seen


def test_a_levels_second_step_may_end_it_at_the_last_levels_rate_of_convergence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    mosaic = make_synthetic(FoldedSurface(seed=7), rows=5, cols=5)
    raw_steps = _steps_recorded(monkeypatch, lambda lv, _: bool(lv.raw))
    carried = pipeline.run(mosaic.patch_set)
    n_carried = sum(raw_steps)
    raw_steps.clear()
    run_level = level.run_level  # what the schedule (icp) calls

    def unknown_rate(fit: Any, *args: Any, **kwargs: Any) -> Any:
        fit.ratio = np.inf  # as if the last level had not told how fast it converged
        return run_level(fit, *args, **kwargs)

    monkeypatch.setattr(icp, "run_level", unknown_rate)
    alone = pipeline.run(mosaic.patch_set)
    # the raw level's first step jumps from the smoothed optimum; the second's ratio to it,
    # held no smaller than the one-pixel level's, says the third is not needed
    assert n_carried == 2 and sum(raw_steps) == 3
    assert carried.iterations == alone.iterations - 1
    # what the third step buys is far below the noise (1 nm)
    e_carried = mosaic.registration_error(carried.transforms)
    e_alone = mosaic.registration_error(alone.transforms)
    assert abs(e_carried[0] - e_alone[0]) < 0.02e-9
    assert abs(e_carried[1] - e_alone[1]) < 0.02e-9


@pytest.mark.parametrize("max_iter", [None, 3])
def test_only_the_widest_level_keeps_its_rows_clear_of_the_patches_borders(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch, max_iter: int | None
) -> None:
    # from the nominal places every level runs, the widest first; a cap on the iterations
    # keeps its band
    bands: list[tuple[float, float]] = []  # the bank's nodes per pixel, the candidates' band
    candidates = SurfaceBank.candidates

    def recorded(bank: SurfaceBank, *args: Any, band: float = 0.0) -> Any:
        bands.append((bank.nodes, band))
        return candidates(bank, *args, band=band)

    monkeypatch.setattr(SurfaceBank, "candidates", recorded)
    steps = _steps_recorded(monkeypatch, lambda lv, _: float(lv.band))
    pipeline.run(small_mosaic.patch_set, MergeConfig(init="nominal", max_iter=max_iter))
    assert DEFAULT_LEVELS[0].band == 4.0 and all(lv.band == 0.0 for lv in DEFAULT_LEVELS[1:])
    # the widest level's steps come first, then the others'
    first = steps.index(0.0)
    assert first > 0 and set(steps[:first]) == {4.0} and set(steps[first:]) == {0.0}
    assert (1, 4.0) in bands and (2, 4.0) not in bands  # never on the raw heights' nodes


def test_a_smoothed_level_holds_patches_the_start_measured_to_a_looser_tolerance(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the paper's grating as a tip draws it: the raw level's optimum lies tenths of a pixel
    # from the one-pixel level's, whose last steps, polishing spins, bought nothing
    grating = tip_drawn_paper_grid()
    smoothed = _steps_recorded(monkeypatch, lambda lv, _: not lv.raw)
    looser = pipeline.run(grating.patch_set)
    n_looser = sum(smoothed)
    smoothed.clear()
    monkeypatch.setattr(level, "MEASURED_TOL", 1.0)
    strict = pipeline.run(grating.patch_set)
    n_strict = sum(smoothed)
    assert n_looser < n_strict  # 7 and 10 steps
    e_looser = grating.registration_error(looser.transforms)
    e_strict = grating.registration_error(strict.transforms)
    assert abs(e_looser[0] - e_strict[0]) < 0.1e-9  # XY 0.68 and 0.69 nm
