"""The refinement's placement state: conversion to and from transforms, and its gauge."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from merge import Patch
from merge.core.transforms import PatchTransform, rotation_about_z
from merge.refine.bank import SurfaceBank
from merge.refine.state import MosaicState

SCALE = 2e-8


def _bank(n: int) -> SurfaceBank:
    rng = np.random.default_rng(0)
    patches = [
        Patch(
            id=f"p{k}",
            heights=rng.normal(0.0, 1e-9, (12, 16)),
            origin=(k * 2.5e-7, (k % 2) * 1e-7),
            pixel_size=(SCALE, SCALE),
            order=k,
        )
        for k in range(n)
    ]
    return SurfaceBank(patches, SCALE, 0.0, 1)


def _transforms(seed: int, n: int) -> list[PatchTransform]:
    rng = np.random.default_rng(seed)
    return [
        PatchTransform(
            rotation_about_z(float(rng.normal(0.0, 0.01))),
            rng.normal(0.0, [5e-8, 5e-8, 2e-8]),
            rng.normal(0.0, 1e-3, 2),
            rng.normal(0.0, 1e-7, 2),
        )
        for _ in range(n)
    ]


def _points() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.uniform([0.0, 0.0, -5e-8], [1e-6, 4e-7, 5e-8], (50, 3))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4))
def test_transforms_survive_the_round_trip_through_the_state(seed: int, n: int) -> None:
    bank = _bank(n)
    start = _transforms(seed, n)
    back = MosaicState.from_transforms(start, bank, SCALE).to_transforms(bank, SCALE)
    p = _points()
    # the drift plane is re-centred on the patch centre: the same map, another constant
    for a, b in zip(start, back, strict=True):
        np.testing.assert_allclose(b.apply(p), a.apply(p), atol=1e-15)


def _moved(state: MosaicState, spin: float, shift: np.ndarray, plane: np.ndarray) -> MosaicState:
    """``state`` under one motion of the whole mosaic (state units), none of which changes a
    residual: a Z plane over it, then a turn about z at the origin and a translation."""
    s = state.s.copy()
    s[:, 2] += s[:, :2] @ plane
    G = rotation_about_z(spin)
    return MosaicState(np.einsum("ij,cjk->cik", G, state.R), s @ G.T + shift, state.slope + plane)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    spin=st.floats(-0.05, 0.05),
    shift=st.tuples(*(st.floats(-20.0, 20.0) for _ in range(3))),
    plane=st.tuples(st.floats(-0.01, 0.01), st.floats(-0.01, 0.01)),
)
def test_the_gauge_removes_any_common_motion(
    seed: int, spin: float, shift: tuple[float, float, float], plane: tuple[float, float]
) -> None:
    bank = _bank(3)
    state = MosaicState.from_transforms(_transforms(seed, 3), bank, SCALE)
    state.fix_gauge(bank.centre, bank.point_count)
    # a gauged mosaic moved as a whole comes back to itself (from an ungauged one only to
    # second order: a plane over the mosaic and a turn about z do not commute)
    moved = _moved(state, spin, np.array(shift), np.array(plane))
    moved.fix_gauge(bank.centre, bank.point_count)
    np.testing.assert_allclose(moved.R, state.R, atol=1e-12)
    np.testing.assert_allclose(moved.s, state.s, atol=1e-9)
    np.testing.assert_allclose(moved.slope, state.slope, atol=1e-12)
    # and the gauge it leaves: no mean spin, no mean plane, no mean displacement
    weight = bank.point_count / bank.point_count.sum()
    assert abs(float(weight @ state.spin())) < 1e-12
    np.testing.assert_allclose(weight @ state.slope, 0.0, atol=1e-12)
    np.testing.assert_allclose(weight @ (state.s - bank.centre), 0.0, atol=1e-9)


def test_a_step_turns_shifts_and_tilts_each_patch_by_its_own_unknowns() -> None:
    bank = _bank(2)
    state = MosaicState.from_transforms([PatchTransform(), PatchTransform()], bank, SCALE)
    s0 = state.s.copy()
    delta = np.zeros((2, 6))
    delta[1] = [0.5, -0.25, 2.0, 0.1, 0.3, -0.2]  # x, y, z, spin and plane at the radius
    radius = np.array([10.0, 20.0])
    state.update(delta, radius)
    np.testing.assert_allclose(state.s - s0, delta[:, :3])
    np.testing.assert_allclose(state.spin(), [0.0, 0.1 / 20.0])
    np.testing.assert_allclose(state.slope, [[0.0, 0.0], [0.3 / 20.0, -0.2 / 20.0]])
