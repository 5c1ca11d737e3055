import math

import numpy as np
import pytest

from hardware.sim.surfaces import Chessboard, FoldedSurface, ImageSurface, TipDrawnChessboard


def test_chessboard_has_the_tgx1_geometry() -> None:
    cb = Chessboard(roughness=0.0)
    # centres of squares: raised and lowered alternately, 0.6 µm apart in height
    low = cb.height(np.array([0.75e-6]), np.array([2.25e-6]))[0]
    high = cb.height(np.array([0.75e-6]), np.array([0.75e-6]))[0]
    assert high - low == pytest.approx(0.6e-6, rel=1e-3)
    # the period is 3 µm
    x = np.linspace(0, 6e-6, 601)
    h = cb.height(x, np.full_like(x, 0.75e-6))
    np.testing.assert_allclose(h[:300], h[300:600], atol=1e-12)
    # edges are rounded: the height passes through the middle over a finite width
    mid = np.abs(h[:150] - 0.3e-6) < 0.2e-6
    assert 5 <= mid.sum() <= 40  # 50 to 400 nm of edge


def test_roughness_is_reproducible_and_of_the_given_size() -> None:
    a, b = Chessboard(seed=3), Chessboard(seed=3)
    x = np.random.default_rng(0).uniform(0, 1e-6, 1000) + 0.5e-6
    y = np.full_like(x, 0.75e-6)
    np.testing.assert_array_equal(a.height(x, y), b.height(x, y))
    plateau = a.height(x, y) - Chessboard(seed=3, roughness=0.0).height(x, y)
    assert 0.7e-9 < plateau.std() < 2.5e-9


def test_folded_surface_has_structure_everywhere() -> None:
    fs = FoldedSurface(seed=1)
    xx, yy = np.meshgrid(np.linspace(0, 8e-6, 81), np.linspace(0, 8e-6, 81))
    h = fs.height(xx, yy)
    assert 50e-9 < h.std() < 400e-9
    # every 1 µm tile has relief well above the noise
    tiles = h[:80, :80].reshape(8, 10, 8, 10).swapaxes(1, 2).reshape(64, 100)
    assert tiles.std(axis=1).min() > 10e-9


def test_image_surface_interpolates_and_is_nan_outside() -> None:
    img = np.arange(20.0).reshape(4, 5) * 1e-9
    s = ImageSurface(img, (1e-8, 2e-8), origin=(1e-6, 0.0))
    assert s.height(np.array([1e-6 + 2e-8]), np.array([2e-8]))[0] == pytest.approx(img[1, 2])
    assert np.isnan(s.height(np.array([0.0]), np.array([0.0]))[0])
    with pytest.raises(ValueError, match="pixel_size"):
        ImageSurface(img, (0.0, 1.0))


@pytest.mark.parametrize(("radius", "angle", "step"), [(10e-9, 14.0, 0.6e-6), (5e-9, 25.0, 0.1e-6)])
def test_a_tip_draws_a_wall_as_its_own_side_turned_over(
    radius: float, angle: float, step: float
) -> None:
    """The image of a raised square's wall: the top flat up to the wall, rounded within the
    apex's reach (a sphere's arc), then a straight flank at the cone's angle down to the
    lower face, which it meets in a kink; the flank spans step * tan(angle)."""
    board = TipDrawnChessboard(tip_radius=radius, half_angle=angle, step=step, roughness=0.0)
    a = board.period / 2
    x = a + np.linspace(-50e-9, board.flank + 50e-9, 4001)  # across the wall at x = a
    y = np.full_like(x, a / 2)  # inside a raised square (left) and a low one (right)
    h = board.height(x, y)
    assert np.all(h[x <= a] == step) and np.all(h[x >= a + board.flank + 1e-12] == 0.0)
    assert np.all(np.diff(h) <= 1e-18)  # never rises going down the wall
    flank = (x > a + radius) & (x < a + board.flank - 1e-9)
    slope = np.diff(h[flank]) / np.diff(x[flank])
    np.testing.assert_allclose(slope, -1 / math.tan(math.radians(angle)), rtol=1e-6)
    arc = (x > a) & (x < a + 0.5 * radius * math.cos(math.radians(angle)))
    np.testing.assert_allclose(
        step - h[arc], radius - np.sqrt(radius**2 - (x[arc] - a) ** 2), atol=1e-15
    )
    # the foot: the slope jumps from the flank's to zero within one sample
    foot = int(np.argmax(h <= 0.0))
    left = (h[foot - 1] - h[foot - 3]) / (x[foot - 1] - x[foot - 3])
    assert left < -0.9 / math.tan(math.radians(angle)) and h[foot + 2] == h[foot] == 0.0


def test_a_tip_drawn_chessboard_alternates_and_refuses_flanks_wider_than_a_square() -> None:
    board = TipDrawnChessboard(roughness=0.0)
    a = board.period / 2
    centres = np.array([0.5, 1.5, 2.5]) * a
    xx, yy = np.meshgrid(centres, centres)
    assert np.array_equal(board.height(xx, yy) > 0, (np.floor(xx / a) + np.floor(yy / a)) % 2 == 0)
    with pytest.raises(ValueError, match="flanks"):
        TipDrawnChessboard(step=4e-6, half_angle=25.0)
