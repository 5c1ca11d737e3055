import numpy as np
import pytest

from merge.core.downsample import grid_downsample


def test_cell_equal_to_pixel_is_identity() -> None:
    h = np.arange(12.0).reshape(3, 4)
    g = grid_downsample(h, (1.0, 1.0), cell=1.0, origin=(5.0, 7.0))
    np.testing.assert_array_equal(g.heights, h)
    np.testing.assert_allclose(g.x, 5.0 + np.arange(4))
    np.testing.assert_allclose(g.y, 7.0 + np.arange(3))


def test_cells_average_and_ignore_nan() -> None:
    h = np.array([[1.0, 3.0, 5.0, np.nan], [1.0, 3.0, np.nan, np.nan]])
    g = grid_downsample(h, (1.0, 1.0), cell=2.0)
    assert g.heights.shape == (1, 2)
    assert g.heights[0, 0] == pytest.approx(2.0)
    assert g.heights[0, 1] == pytest.approx(5.0)
    assert g.counts.tolist() == [[4, 1]]
    # cell centres sit in the middle of the cells
    assert g.x.tolist() == pytest.approx([0.5, 2.5])
    pts, flat = g.points()
    assert pts.shape == (2, 3) and flat.tolist() == [0, 1]


def test_empty_cell_is_nan_and_anisotropic_pixels() -> None:
    h = np.ones((2, 8))
    h[:, 2:4] = np.nan
    g = grid_downsample(h, (0.5, 1.0), cell=1.0)  # two pixels per cell along x
    assert g.heights.shape == (2, 4)
    assert np.isnan(g.heights[:, 1]).all()
    assert np.isfinite(g.heights[:, [0, 2, 3]]).all()


def test_common_anchor_puts_patches_on_one_lattice() -> None:
    h = np.zeros((4, 4))
    a = grid_downsample(h, (1.0, 1.0), cell=2.0, origin=(0.0, 0.0), anchor=(-0.5, -0.5))
    b = grid_downsample(h, (1.0, 1.0), cell=2.0, origin=(2.0, 0.0), anchor=(-0.5, -0.5))
    assert b.x[0] - a.x[0] == pytest.approx(2.0)


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="cell"):
        grid_downsample(np.zeros((2, 2)), (1.0, 1.0), cell=0.0)
    with pytest.raises(ValueError, match="2-D"):
        grid_downsample(np.zeros(4), (1.0, 1.0), cell=1.0)
