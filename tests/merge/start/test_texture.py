"""The shift along a straight edge, measured on the texture beside it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from merge.start.lattice import coherence
from merge.start.peaks import CorrelationPeak
from merge.start.texture import ISOTROPIC, along_edge, texture_image

ALONG_Y = np.array([0.0, 1.0])


def _field(seed: int, rough: float = 4e-9) -> np.ndarray:
    """A step along y (its ramp across columns 38-42) with roughness beside it, 90 x 80 cells."""
    rng = np.random.default_rng(seed)
    cols = np.arange(80.0)
    step = np.tile(300e-9 * np.tanh((cols - 40.0) / 1.5), (90, 1))
    return step + gaussian_filter(rng.normal(0.0, rough, step.shape), 1.0)


def _pair(field: np.ndarray, dy: int, seed: int, noise: float = 0.5e-9) -> tuple:
    """Images a and b of ``field``, b's rows ``dy`` further on: ``b[y - dy] = a[y]``."""
    rng = np.random.default_rng(seed)
    a = field[20:70] + rng.normal(0.0, noise, (50, 80))
    b = field[20 + dy : 70 + dy] + rng.normal(0.0, noise, (50, 80))
    return a, b


def _texture(image: np.ndarray) -> np.ndarray:
    tex = texture_image(image)
    assert tex is not None  # a roughness
    return tex


def _along_y(a: np.ndarray, b: np.ndarray) -> float | None:
    """:func:`along_edge` of images ``a`` and ``b`` along y from a peak at (0, 0), by the
    start's rules."""
    return along_edge(
        _texture(a),
        _texture(b),
        _peak_at((0, 0)),
        ALONG_Y,
        radius=10,
        min_overlap=200,
        accept=0.3,
        significance=3.0,
        ambiguity=0.1,
    )


def _peak_at(shift: tuple[int, int]) -> CorrelationPeak:
    return CorrelationPeak(
        shift=(float(shift[0]), float(shift[1])),
        integer_shift=shift,
        score=0.9,
        overlap=1000,
        at_border=False,
        window=np.zeros(1),
    )


def test_the_texture_is_the_roughness_with_the_step_masked() -> None:
    field = _field(0)
    tex = _texture(field)
    assert np.isnan(tex[:, 37:44]).all()  # the ramp and a margin about it
    faces = np.isfinite(tex)
    assert faces[:, :28].all() and faces[:, 52:].all()  # the faces beyond the margin
    assert np.nanstd(tex) < 3e-9  # roughness, not the 600 nm step


@pytest.mark.parametrize(("dy", "seed"), [(7, 1), (-5, 2), (3, 3)])
def test_along_an_edge_the_texture_finds_the_shift_the_edge_left_open(dy: int, seed: int) -> None:
    a, b = _pair(_field(seed), dy, seed + 10)
    # the edge's peak, at the wrong place along the edge: b[y + s] = a[y] at s = -dy
    moved = _along_y(a, b)
    assert moved is not None
    assert moved == pytest.approx(-dy, abs=0.3)


def test_a_bare_edge_under_noise_measures_nothing_along_it() -> None:
    a, b = _pair(_field(4, rough=0.0), 6, 14, noise=1e-9)
    assert _along_y(a, b) is None


def test_stripes_a_few_cells_wide_are_structure_not_texture() -> None:
    # a grating whose stripes outlive the smoothing's removal: every shift along them scored
    # alike (0.98), so they are no texture to measure the shift along them with
    rng = np.random.default_rng(6)
    yy, xx = np.mgrid[0:90, 0:80].astype(float)
    field = 50e-9 * np.sin(2 * np.pi * (xx - yy) / 6.0) + rng.normal(0.0, 0.3e-9, xx.shape)
    assert texture_image(field) is None
    rough = _field(7)[:, :30]  # roughness beside a step
    assert coherence(_texture(rough)) < ISOTROPIC
