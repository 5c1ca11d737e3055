"""Invariants of the merge: where the stage frame starts, and in which order patches are listed,
must not change the relative solution."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from merge import Patch, PatchSet, run
from tests.conftest import Synthetic


def _corrections(result: object, patch_set: PatchSet) -> np.ndarray:
    """Each patch's displacement of its centre point, relative to patch 0's."""
    out = []
    for p, rep in zip(patch_set, result.patches, strict=True):  # type: ignore[attr-defined]
        c = np.array([*p.center, float(np.nanmedian(p.heights))])
        out.append(rep.transform.apply(c[None])[0] - c)
    arr = np.array(out)
    return arr - arr[0]


@settings(
    max_examples=4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.floats(-2e-3, 2e-3), st.floats(-2e-3, 2e-3), st.floats(-5e-6, 5e-6))
def test_moving_the_whole_set_moves_nothing_relative(
    small_mosaic: Synthetic, dx: float, dy: float, dz: float
) -> None:
    base = small_mosaic.patch_set
    moved = PatchSet(
        Patch(
            id=p.id,
            heights=p.heights + dz,
            origin=(p.origin[0] + dx, p.origin[1] + dy),
            pixel_size=p.pixel_size,
            order=p.order,
        )
        for p in base
    )
    a = _corrections(run(base), base)
    b = _corrections(run(moved), moved)
    np.testing.assert_allclose(b, a, atol=0.05e-9)


def test_listing_order_does_not_change_the_solution(small_mosaic: Synthetic) -> None:
    base = small_mosaic.patch_set
    relabelled = PatchSet(
        Patch(
            id=p.id,
            heights=p.heights,
            origin=p.origin,
            pixel_size=p.pixel_size,
            order=len(base) - 1 - p.order,
        )
        for p in base
    )
    a = {p.id: r.transform.t for p, r in zip(base, run(base).patches, strict=True)}
    b = {p.id: r.transform.t for p, r in zip(relabelled, run(relabelled).patches, strict=True)}
    for pid in a:
        np.testing.assert_allclose(b[pid] - b["p000"], a[pid] - a["p000"], atol=0.05e-9)
    assert set(a) == set(b)


def test_a_noise_free_set_is_registered_exactly() -> None:
    from hardware.sim.drift import DriftModel
    from hardware.sim.surfaces import FoldedSurface
    from tests.conftest import make_synthetic

    clean = DriftModel(
        stage_sigma=40e-9,
        rotation_sigma_deg=0.3,
        z_step_mean=30e-9,
        z_step_sigma=20e-9,
        z_drift_sigma=0.0,
        noise=0.0,
        line_noise=0.0,
    )
    syn = make_synthetic(FoldedSurface(seed=5), drift=clean, seed=4)
    exy, ez = syn.registration_error(run(syn.patch_set).transforms)
    assert exy < 0.3e-9
    assert ez == pytest.approx(0.0, abs=0.1e-9)
