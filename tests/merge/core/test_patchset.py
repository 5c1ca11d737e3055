import numpy as np
import pytest

from merge import Patch, PatchSet, PatchSetError
from merge.core.noise import estimate_noise


def make(pid: str = "p0", shape: tuple[int, int] = (4, 5), **kw: object) -> Patch:
    args: dict[str, object] = {
        "id": pid,
        "heights": np.zeros(shape),
        "origin": (0.0, 0.0),
        "pixel_size": (1e-8, 2e-8),
    }
    args.update(kw)
    return Patch(**args)  # type: ignore[arg-type]


def test_geometry_follows_the_pixel_convention() -> None:
    p = make(shape=(3, 4), origin=(1e-6, 2e-6))
    assert p.shape == (3, 4)
    assert p.extent == pytest.approx((3e-8, 4e-8))
    assert p.footprint == pytest.approx((1e-6, 2e-6, 1e-6 + 3e-8, 2e-6 + 4e-8))
    xx, yy = p.pixel_coordinates()
    assert xx[0, 3] == pytest.approx(1e-6 + 3e-8)  # column j along x
    assert yy[2, 0] == pytest.approx(2e-6 + 4e-8)  # row i along y


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"heights": np.zeros(5)}, "2-D"),
        ({"heights": np.zeros((2, 2, 2))}, "2-D"),
        ({"heights": np.full((3, 3), np.nan)}, "all NaN"),
        ({"heights": np.array([[0.0, np.inf], [0.0, 0.0]])}, "infinite"),
        ({"heights": np.zeros((1, 5))}, "2 x 2"),
        ({"pixel_size": (0.0, 1e-8)}, "positive"),
        ({"pixel_size": (1e-8, -1e-8)}, "positive"),
        ({"pixel_size": (1e-8,)}, "two finite numbers"),
        ({"origin": ("a", 0)}, "two numbers"),
        ({"heights": np.array([["a", "b"], ["c", "d"]])}, "real numbers"),
    ],
)
def test_bad_patches_are_named_errors(kwargs: dict[str, object], message: str) -> None:
    with pytest.raises(PatchSetError, match=message) as err:
        make("bad-one", **kwargs)
    assert "bad-one" in str(err.value)


def test_patch_set_needs_two_unique_patches_and_sorts_by_order() -> None:
    with pytest.raises(PatchSetError, match="at least two"):
        PatchSet([make()])
    with pytest.raises(PatchSetError, match="more than once"):
        PatchSet([make("a"), make("a")])
    ps = PatchSet([make("b", order=1), make("a", order=0)])
    assert ps.ids == ["a", "b"]
    assert ps.subset(["b", "a"]).ids == ["a", "b"]
    with pytest.raises(PatchSetError, match="no patch"):
        ps.subset(["zz"])


def test_median_height_and_noise_are_the_patch_heights_own_computed_once() -> None:
    rng = np.random.default_rng(3)
    heights = 1e-8 * np.add.outer(np.arange(32.0), np.arange(40.0)) + rng.normal(0, 1e-9, (32, 40))
    heights[5, 7] = np.nan
    p = Patch("a", heights, (0.0, 0.0), (1e-8, 1e-8))
    assert p.median_height == float(np.nanmedian(heights))
    assert p.noise == estimate_noise(heights)
    assert p.noise == pytest.approx(1e-9, rel=0.15)  # a plane's second differences vanish
    assert "noise" in vars(p) and "median_height" in vars(p)  # kept on the patch
