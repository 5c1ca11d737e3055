"""Patches as continuous surfaces: look-ups and candidate correspondences."""

from __future__ import annotations

import numpy as np

from merge.bank import SurfaceBank
from merge.patchset import Patch


def _plane_patch(pid: str, origin: tuple[float, float]) -> Patch:
    yy, xx = np.mgrid[0:20, 0:30].astype(np.float64)
    # heights in metres over 10 nm pixels: slope 0.3 along x, -0.2 along y
    heights = (0.3 * xx - 0.2 * yy) * 10e-9 + 50e-9
    return Patch(id=pid, heights=heights, origin=origin, pixel_size=(10e-9, 10e-9))


def test_lookup_is_exact_on_a_plane_and_refuses_points_outside() -> None:
    bank = SurfaceBank([_plane_patch("a", (0.0, 0.0))], 10e-9, 0.0, 1)
    rng = np.random.default_rng(0)
    half = bank.half[0]
    inside = rng.uniform(-half, half, size=(200, 2))
    outside = np.array([[half[0] + 0.5, 0.0], [0.0, -half[1] - 0.5]])
    pts = np.vstack([inside, outside])
    h, gx, gy, ok = bank.lookup(
        np.zeros(len(pts), dtype=np.intp), np.column_stack([pts, 0 * pts[:, 0]])
    )
    assert ok[:200].all() and not ok[200:].any()
    # local heights: relative to the patch median, pixel units
    expected = (
        0.3 * (pts[:200, 0] + half[0]) - 0.2 * (pts[:200, 1] + half[1]) + 5.0 - bank.centre[0, 2]
    )
    np.testing.assert_allclose(h[:200], expected, atol=1e-9)
    np.testing.assert_allclose(gx[:200], 0.3, atol=1e-9)
    np.testing.assert_allclose(gy[:200], -0.2, atol=1e-9)


def test_lookup_is_not_valid_next_to_a_hole() -> None:
    p = _plane_patch("a", (0.0, 0.0))
    heights = p.heights.copy()
    heights[10, 15] = np.nan
    bank = SurfaceBank([Patch("a", heights, p.origin, p.pixel_size)], 10e-9, 0.0, 1)
    # local coordinates of pixel (row 10, column 15) and of a far corner
    node = np.array(
        [
            [15 - bank.half[0, 0], 10 - bank.half[0, 1], 0.0],
            [-bank.half[0, 0] + 1, -bank.half[0, 1] + 1, 0.0],
        ]
    )
    _, _, _, ok = bank.lookup(np.zeros(2, dtype=np.intp), node)
    assert not ok[0] and ok[1]


def test_candidates_come_in_contiguous_runs_of_each_directed_pair() -> None:
    # two patches overlapping by a third along x
    a = _plane_patch("a", (0.0, 0.0))
    b = _plane_patch("b", (200e-9, 0.0))
    bank = SurfaceBank([a, b], 10e-9, 0.0, 1)
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    s = bank.centre.copy()
    src, dst, idx, starts = bank.candidates(np.array([[0, 1]]), R, s, 0.0)
    assert list(starts) == [0, starts[1], len(idx)]
    assert (src[: starts[1]] == 0).all() and (dst[: starts[1]] == 1).all()
    assert (src[starts[1] :] == 1).all() and (dst[starts[1] :] == 0).all()
    # patch a's points at x >= 200 nm: columns 20..29 of 20 rows
    assert starts[1] == 10 * 20
    assert len(idx) - starts[1] == 10 * 20
    assert (idx[: starts[1]] < bank.point_start[1]).all()
    assert (idx[starts[1] :] >= bank.point_start[1]).all()
