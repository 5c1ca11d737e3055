"""Registration of a topography onto an SEM image recovers the simulator's hidden SEM map
(rotation, scale, offset) for a mosaic and for one patch, on the folded and the grating
samples, and refuses what it cannot trust."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hardware.microscope import SIM_SAMPLE_SIZE
from hardware.sim.sem import SEMGeometry, SimulatedSEM, render_frame
from hardware.sim.surfaces import Chessboard, surface_by_name
from merge.correlative import SEMView, Similarity, register_to_sem
from merge.correlative.correlate import best_peak, masked_ncc

FIELD, PIXELS = 20e-6, 1024
PITCH = FIELD / PIXELS
#: the SEM as the simulator hides it: turned, scaled and off-centre against the stage
HIDDEN = SEMGeometry(rotation=3.0, scale=1.025, offset=(0.3e-6, -0.2e-6))


@pytest.fixture(scope="module")
def folded() -> Any:
    return surface_by_name("folded", seed=0, centred=True, size=SIM_SAMPLE_SIZE)


def _nominal(image: np.ndarray) -> SEMView:
    """The SEM image placed by its nominal pixel, centred on the stage's origin, rows down."""
    middle = (PIXELS - 1) / 2
    return SEMView(image, (-middle * PITCH, middle * PITCH), np.diag([PITCH, -PITCH]))


def _truth(points: np.ndarray, geometry: SEMGeometry) -> np.ndarray:
    """Where the nominally placed image shows stage points (the map a registration finds)."""
    pixel = geometry.frame_pixels(points, field=FIELD, pixels=PIXELS)
    return _nominal(np.zeros((1, 1))).to_stage(pixel[:, 0], pixel[:, 1])


def _mosaic(surface: Any, x0: float, y0: float, width: float, height: float) -> np.ndarray:
    xx, yy = np.meshgrid(
        x0 + np.arange(round(width / 10e-9)) * 10e-9, y0 + np.arange(round(height / 10e-9)) * 10e-9
    )
    out: np.ndarray = surface.height(xx, yy)
    return out


def _corners(x0: float, y0: float, width: float, height: float) -> np.ndarray:
    return np.array([[x0, y0], [x0 + width, y0], [x0, y0 + height], [x0 + width, y0 + height]])


@pytest.mark.parametrize(
    ("where", "size"),
    [((1e-6, -3e-6), (4e-6, 6e-6)), ((-4e-6, 2e-6), (1e-6, 1e-6))],
    ids=["mosaic of 50 patches", "one patch"],
)
def test_the_hidden_sem_map_is_recovered_on_the_folded_sample(
    folded: Any, where: tuple[float, float], size: tuple[float, float]
) -> None:
    sem = SimulatedSEM(folded, seed=3, geometry=HIDDEN)
    image = render_frame(sem, HIDDEN, field=FIELD, pixels=PIXELS)
    steps: list[tuple[int, float]] = []
    found = register_to_sem(
        _mosaic(folded, *where, *size),
        _nominal(image),
        origin=where,
        pixel_size=(10e-9, 10e-9),
        callback=lambda k, rms: steps.append((k, rms)),
    )
    assert found.accepted, found.reason
    corners = _corners(*where, *size)
    misplaced = np.hypot(*(found.transform.apply(corners) - _truth(corners, HIDDEN)).T) / PITCH
    assert misplaced.max() < 1.0, misplaced  # the bound: one SEM pixel
    assert abs(found.transform.rotation_deg + HIDDEN.rotation) < 0.1  # and 0.1 degree
    assert found.score > 0.7 and steps and steps[-1][1] <= steps[0][1]
    # the shading found is the simulated detector's: it sits towards +x +y, so faces whose
    # normals turn that way (slopes falling towards it) are brighter, both weights negative
    assert found.weights[2] < 0 and found.weights[2] == pytest.approx(found.weights[3], rel=0.3)


def test_a_grating_is_registered_from_a_calibrated_prior_and_refused_without_one() -> None:
    board = Chessboard()
    sem = SimulatedSEM(board, seed=2, geometry=HIDDEN)
    image = render_frame(sem, HIDDEN, field=FIELD, pixels=PIXELS)
    where, size = (-2e-6, -1e-6), (4e-6, 3e-6)
    heights = _mosaic(board, *where, *size)
    corners = _corners(*where, *size)
    # a prior as a calibration gives it: the truth within a pixel, the search narrowed to it
    exact = np.column_stack([corners, np.ones(4)])
    solution, *_ = np.linalg.lstsq(exact, _truth(corners, HIDDEN), rcond=None)
    m = solution[:2].T
    prior = Similarity(
        math.degrees(math.atan2(m[1, 0], m[0, 0])) + 0.03,
        math.sqrt(abs(np.linalg.det(m))),
        (solution[2, 0] + 0.7 * PITCH, solution[2, 1] - 0.5 * PITCH),
    )
    found = register_to_sem(
        heights,
        _nominal(image),
        origin=where,
        pixel_size=(10e-9, 10e-9),
        prior=prior,
        search_shift=0.3e-6,
        search_rotation=0.5,
        search_scale=0.01,
    )
    assert found.accepted, found.reason
    misplaced = np.hypot(*(found.transform.apply(corners) - _truth(corners, HIDDEN)).T) / PITCH
    assert misplaced.max() < 1.0
    wide = register_to_sem(heights, _nominal(image), origin=where, pixel_size=(10e-9, 10e-9))
    assert not wide.accepted and "periodic" in str(wide.reason)


def test_a_featureless_sample_and_a_mosaic_off_the_image_are_refused() -> None:
    flat = Chessboard(step=0.0, roughness=0.2e-9)  # roughness under the SEM's noise
    sem = SimulatedSEM(flat, seed=1, geometry=HIDDEN)
    view = _nominal(render_frame(sem, HIDDEN, field=FIELD, pixels=PIXELS))
    heights = _mosaic(flat, -1e-6, -1e-6, 3e-6, 3e-6)
    found = register_to_sem(heights, view, origin=(-1e-6, -1e-6), pixel_size=(10e-9, 10e-9))
    assert not found.accepted and "too little structure" in str(found.reason)
    away = register_to_sem(heights, view, origin=(30e-6, 0.0), pixel_size=(10e-9, 10e-9))
    assert not away.accepted and "lies in the SEM image" in str(away.reason)
    with pytest.raises(ValueError, match="search_rotation"):
        register_to_sem(heights, view, origin=(0, 0), pixel_size=(1e-8, 1e-8), search_rotation=90)


@settings(max_examples=25, deadline=None)
@given(
    rotation=st.floats(-180, 180),
    scale=st.floats(0.5, 2.0),
    offset=st.tuples(st.floats(-1e-3, 1e-3), st.floats(-1e-3, 1e-3)),
)
def test_a_similarity_inverts_what_it_applies(
    rotation: float, scale: float, offset: tuple[float, float]
) -> None:
    t = Similarity(rotation, scale, offset)
    points = np.array([[0.0, 0.0], [1e-6, -2e-6], [3e-5, 4e-5]])
    np.testing.assert_allclose(t.invert(t.apply(points)), points, atol=1e-15)


@settings(max_examples=20, deadline=None)
@given(dr=st.integers(-5, 5), dc=st.integers(-5, 5), seed=st.integers(0, 2**16))
def test_masked_correlation_finds_where_a_template_lies(dr: int, dc: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    image = rng.normal(size=(48, 48))
    mask = np.zeros((48, 48), dtype=bool)
    mask[12:36, 14:30] = True
    template = np.roll(image, (-dr, -dc), axis=(0, 1))  # its content dr rows, dc columns on
    peak = best_peak(masked_ncc(template, mask, image, radius=8), apart=3)
    assert (round(peak.rows), round(peak.columns)) == (dr, dc)
    assert peak.score == pytest.approx(1.0) and peak.rival < 0.5


def test_a_rival_along_a_ridge_is_told_from_a_rival_apart() -> None:
    """A lone edge matches all along itself (a ridge of correlation: the match slides); a
    periodic structure matches again one period away (a peak apart, a dip between)."""
    rng = np.random.default_rng(3)
    edge = np.zeros((64, 64))
    edge[:, 32:] = 1.0
    mask = np.zeros((64, 64), dtype=bool)
    mask[16:48, 16:48] = True
    lone = best_peak(
        masked_ncc(edge, mask, edge + rng.normal(0, 0.05, edge.shape), radius=10), apart=4
    )
    assert lone.rival > 0.9 * lone.score and lone.ridge
    xx = np.arange(64)[None, :] * np.ones((64, 1))
    yy = xx.T
    bumps = np.exp(-(((xx % 8) - 4) ** 2 + ((yy % 40) - 20) ** 2) / 8.0)
    noisy = bumps + rng.normal(0, 0.05, bumps.shape)
    periodic = best_peak(masked_ncc(bumps, mask, noisy, radius=10), apart=4)
    assert periodic.rival > 0.9 * periodic.score and not periodic.ridge


def test_an_affine_fit_finds_a_sheared_sem(folded: Any) -> None:
    """An SEM whose scan is sheared (its axes 0.5 degree from square) is found by the affine
    fit, where the similarity can only average it."""
    sem = SimulatedSEM(folded, seed=5, geometry=HIDDEN)
    image = render_frame(sem, HIDDEN, field=FIELD, pixels=PIXELS)
    shear = math.tan(math.radians(0.5))
    middle = (PIXELS - 1) / 2
    sheared = SEMView(
        image, (-middle * PITCH, middle * PITCH), np.array([[PITCH, shear * -PITCH], [0.0, -PITCH]])
    )
    where, size = (-1.5e-6, -2e-6), (4e-6, 5e-6)
    heights = _mosaic(folded, *where, *size)
    found = register_to_sem(heights, sheared, origin=where, pixel_size=(10e-9, 10e-9), affine=True)
    assert found.accepted, found.reason
    assert found.affine is not None
    corners = _corners(*where, *size)
    pixel = HIDDEN.frame_pixels(corners, field=FIELD, pixels=PIXELS)
    truth = sheared.to_stage(pixel[:, 0], pixel[:, 1])
    placed = corners @ found.affine[:, :2].T + found.affine[:, 2]
    affine_error = np.hypot(*(placed - truth).T).max()
    similar = register_to_sem(heights, sheared, origin=where, pixel_size=(10e-9, 10e-9))
    similar_error = np.hypot(*(similar.transform.apply(corners) - truth).T).max()
    assert affine_error < 0.5 * PITCH and affine_error < 0.5 * similar_error
