import numpy as np
import pytest

from merge import Patch, PatchTransform, render_mosaic
from merge.core.transforms import rotation_about_z


def plane_patch(pid: str, origin: tuple[float, float], shape: tuple[int, int] = (20, 30)) -> Patch:
    ny, nx = shape
    xx, yy = np.meshgrid(origin[0] + np.arange(nx) * 1e-8, origin[1] + np.arange(ny) * 1e-8)
    return Patch(id=pid, heights=0.01 * xx + 0.02 * yy, origin=origin, pixel_size=(1e-8, 1e-8))


def test_nominal_render_reproduces_a_plane_and_blends_overlaps() -> None:
    a = plane_patch("a", (0.0, 0.0))
    b = plane_patch("b", (1.5e-7, 0.0))
    m = render_mosaic([a, b])
    ny, nx = m.heights.shape
    assert (ny, nx) == (20, 45)
    xx, yy = np.meshgrid(np.arange(nx) * 1e-8, np.arange(ny) * 1e-8)
    np.testing.assert_allclose(m.heights, 0.01 * xx + 0.02 * yy, atol=1e-15)
    assert m.coverage[:, 15:30].min() == 2 and m.coverage[:, :15].max() == 1


def test_a_translation_moves_the_content_and_outside_is_nan() -> None:
    a = plane_patch("a", (0.0, 0.0))
    b = plane_patch("b", (1e-6, 0.0))  # far away: a gap between the two
    shift = PatchTransform(t=np.array([2e-8, 0.0, 1e-9]))
    m = render_mosaic([a, b], [shift, PatchTransform()])
    assert m.origin[0] == pytest.approx(2e-8)
    assert np.isnan(m.heights[:, 40]).all()
    # a's pixel j now lies at x = j*dx + 2e-8, with its height plus 1 nm
    assert m.heights[0, 0] == pytest.approx(0.0 + 1e-9)


def test_rotation_and_drift_plane_are_applied() -> None:
    a = plane_patch("a", (0.0, 0.0), (41, 41))
    flat = Patch(id="f", heights=np.zeros((41, 41)), origin=(0.0, 0.0), pixel_size=(1e-8, 1e-8))
    tr = PatchTransform(rotation_about_z(np.radians(90)), np.array([4e-7, 0.0, 0.0]))
    m = render_mosaic([a], [tr])
    # a quarter turn: the x-slope becomes a y-slope
    gy, gx = np.gradient(m.heights, 1e-8)
    assert np.nanmedian(gx) == pytest.approx(-0.02, rel=1e-6)
    assert np.nanmedian(gy) == pytest.approx(0.01, rel=1e-6)
    drift = PatchTransform(slope=np.array([1e-3, 0.0]), centre=np.array([2e-7, 2e-7]))
    m2 = render_mosaic([flat], [drift])
    assert m2.heights[0, 0] == pytest.approx(-2e-10)
    assert m2.heights[0, 40] == pytest.approx(2e-10)


def test_bad_options() -> None:
    a = plane_patch("a", (0.0, 0.0))
    with pytest.raises(ValueError, match="one transform per patch"):
        render_mosaic([a], [])
    with pytest.raises(ValueError, match="feather"):
        render_mosaic([a], feather=0.9)
