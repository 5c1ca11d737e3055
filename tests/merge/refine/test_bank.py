"""Patches as continuous surfaces: look-ups and candidate correspondences."""

from __future__ import annotations

import numpy as np
import pytest

from merge import run
from merge.core.patchset import Patch
from merge.refine import bank as bank_module
from merge.refine import normal_system
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState, residuals
from tests.conftest import Synthetic


def _plane_patch(pid: str, origin: tuple[float, float]) -> Patch:
    yy, xx = np.mgrid[0:20, 0:30].astype(np.float64)
    # heights in metres over 10 nm pixels: slope 0.3 along x, -0.2 along y
    heights = (0.3 * xx - 0.2 * yy) * 10e-9 + 50e-9
    return Patch(id=pid, heights=heights, origin=origin, pixel_size=(10e-9, 10e-9))


@pytest.mark.parametrize("smooth", [0.0, 1.0, 2.0])
def test_lookup_is_exact_on_a_plane_and_refuses_points_outside(smooth: float) -> None:
    # raw heights (spline nodes at half pixels) and smoothed ones (bilinear between pixels),
    # every level up to the border: there the patches overlap
    bank = SurfaceBank([_plane_patch("a", (0.0, 0.0))], 10e-9, smooth, 1)
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
        0.3 * (pts[:200, 0] + bank.half[0, 0])
        - 0.2 * (pts[:200, 1] + bank.half[0, 1])
        + 5.0
        - bank.centre[0, 2]
    )
    # the nodes are stored in float32: a millionth of a pixel on heights of a few pixels
    np.testing.assert_allclose(h[:200], expected, atol=3e-6)
    # and the slopes, differences of those nodes a pixel apart
    np.testing.assert_allclose(gx[:200], 0.3, atol=3e-6)
    np.testing.assert_allclose(gy[:200], -0.2, atol=3e-6)


def test_raw_slopes_at_the_pixels_are_their_central_differences() -> None:
    # the spline's slopes reduce to what the bilinear look-ups had at the pixels (one-sided at
    # the border), so only what lies between pixels changes
    rng = np.random.default_rng(3)
    heights = rng.normal(0.0, 1e-9, (12, 16)).cumsum(axis=1)
    patch = Patch("a", heights, (0.0, 0.0), (1e-9, 1e-9))
    bank = SurfaceBank([patch], 1e-9, 0.0, 1)
    yy, xx = np.mgrid[0:12, 0:16]
    pts = np.column_stack(
        [xx.ravel() - bank.half[0, 0], yy.ravel() - bank.half[0, 1], 0 * xx.ravel()]
    )
    h, gx, gy, ok = bank.lookup(np.zeros(len(pts), dtype=np.intp), pts.astype(np.float64))
    ey, ex = np.gradient(heights * 1e9)
    assert ok.all()
    np.testing.assert_allclose(h, (heights * 1e9 - bank.centre[0, 2]).ravel(), atol=1e-9)
    np.testing.assert_allclose(gx, ex.ravel(), atol=1e-6)
    np.testing.assert_allclose(gy, ey.ravel(), atol=1e-6)


def test_every_level_places_a_patch_in_the_same_frame() -> None:
    # a two-level face (a grating's top and bottom): smoothing moves its median, which must not
    # move the frame a placement refers to, or every level begins with patches jumped in Z
    yy, xx = np.mgrid[0:20, 0:30].astype(np.float64)
    heights = np.where(xx + 0.3 * yy < 15.0, 0.0, 100e-9) + 1e-9 * np.sin(xx * yy)
    patch = Patch("a", heights, (0.0, 0.0), (10e-9, 10e-9))
    raw, smooth = SurfaceBank([patch], 10e-9, 0.0, 1), SurfaceBank([patch], 10e-9, 2.0, 2)
    np.testing.assert_array_equal(smooth.centre, raw.centre)


def test_raw_lookups_follow_roughness_between_pixels_better_than_bilinear() -> None:
    # a surface with texture at the scale of two pixels, sampled on whole pixels and looked up
    # halfway between them: bilinear shaves the roughness, the spline follows it
    yy, xx = np.mgrid[0:40, 0:40].astype(np.float64)
    wave = lambda x, y: np.sin(1.6 * x + 0.3) * np.cos(1.3 * y)  # noqa: E731
    patch = Patch("a", wave(xx, yy) * 1e-9, (0.0, 0.0), (1e-9, 1e-9))
    raw = SurfaceBank([patch], 1e-9, 0.0, 1)
    rng = np.random.default_rng(1)
    uv = rng.uniform(4.0, 35.0, size=(500, 2))
    pts = np.column_stack([uv - raw.half[0], np.zeros(500)])
    h, _, _, ok = raw.lookup(np.zeros(500, dtype=np.intp), pts)
    truth = wave(uv[:, 0], uv[:, 1]) - raw.centre[0, 2]
    spline_err = np.sqrt(np.mean((h[ok] - truth[ok]) ** 2))
    # bilinear between the same pixels
    i0, j0 = np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)
    fv, fu = uv[:, 1] - i0, uv[:, 0] - j0
    z = patch.heights * 1e9 - raw.centre[0, 2]
    bil = (1 - fv) * ((1 - fu) * z[i0, j0] + fu * z[i0, j0 + 1]) + fv * (
        (1 - fu) * z[i0 + 1, j0] + fu * z[i0 + 1, j0 + 1]
    )
    bil_err = np.sqrt(np.mean((bil - truth) ** 2))
    assert ok.all()
    assert spline_err < 0.4 * bil_err


def _flank(x: np.ndarray, y: np.ndarray, phase: float) -> np.ndarray:
    """A tip-drawn step 0.6 µm high (metres, 20 nm pixels as x, y in pixels): flat, a straight
    flank of slope 4 over 7.5 px, flat; its edges 2° off the columns, ``phase`` px along x."""
    across = (x + phase) * np.cos(np.radians(2.0)) + y * np.sin(np.radians(2.0))
    out: np.ndarray = 20e-9 * 4.0 * np.clip(across - 10.0, 0.0, 7.5)
    return out


@pytest.mark.parametrize("phase", [0.0, 0.3, 0.5, 0.8])
def test_raw_lookups_draw_a_tip_drawn_edge_as_it_is_wherever_its_kinks_fall(phase: float) -> None:
    # the spline rings at the flank's kinks by an amount that depends on where they fall
    # between the pixels (so two patches of one edge disagree); the sub-cell reconstruction
    # draws both straight pieces and the kink where they meet
    yy, xx = np.mgrid[0:24, 0:36].astype(np.float64)
    patch = Patch("a", _flank(xx, yy, phase), (0.0, 0.0), (20e-9, 20e-9))
    rng = np.random.default_rng(2)
    uv = rng.uniform(4.0, 19.0, size=(2000, 2)) * [1.5, 1.0]
    pts = np.column_stack([uv - SurfaceBank([patch], 20e-9, 0.0, 1).half[0], np.zeros(2000)])
    errors = {}
    for subcell in (False, True):
        bank = SurfaceBank([patch], 20e-9, 0.0, 1)
        if not subcell:
            bank.kinks = None
        h, _, _, ok = bank.lookup(np.zeros(2000, dtype=np.intp), pts)
        truth = _flank(uv[:, 0], uv[:, 1], phase) / 20e-9 - bank.centre[0, 2]
        assert ok.all()
        errors[subcell] = np.abs(h - truth).max() * 20.0  # nm
    assert errors[False] > 1.0  # nanometres of ringing
    assert errors[True] < 1e-2  # a hundredth of a nanometre: the ringing beyond RINGING


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
    runs = bank.candidates(np.array([[0, 1]]), R, s, 0.0)
    rows = bank.rows(runs)
    assert runs.src.tolist() == [0, 1] and runs.dst.tolist() == [1, 0]
    # patch a's points at x >= 200 nm: columns 20..29 of 20 rows, and b's at x <= 90 nm
    assert runs.starts.tolist() == [0, 10 * 20, 2 * 10 * 20]
    assert set(rows.col[:200].tolist()) == set(range(20, 30))
    assert set(rows.col[200:].tolist()) == set(range(10))
    assert (rows.src[:200] == 0).all() and (rows.dst[200:] == 0).all()
    # line by line within a run: every line of a run is one group
    assert (np.diff(rows.row[:200]) >= 0).all()
    assert rows.groups.tolist() == list(range(0, 400, 10))


def test_runs_hold_exactly_the_points_inside_a_rotated_outline() -> None:
    # a strided grid, a turned and shifted destination: the run's rectangle is every point of
    # the source inside the destination's bounding box in the source's frame, no more
    a = _plane_patch("a", (0.0, 0.0))
    b = _plane_patch("b", (130e-9, 70e-9))
    bank = SurfaceBank([a, b], 10e-9, 1.0, 2)
    t = 0.1
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    R[1, :2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    s = bank.centre.copy()
    runs = bank.candidates(np.array([[0, 1]]), R, s, 0.7)
    rows = bank.rows(runs, 0, 1)
    xyz = bank.point_xyz(rows)
    hx, hy = bank.half[1]
    corners = np.array([[-hx, -hy, 0], [hx, -hy, 0], [hx, hy, 0], [-hx, hy, 0]])
    loc = (corners @ R[1].T + s[1] - s[0]) @ R[0]
    lo, hi = loc[:, :2].min(axis=0) - 0.7, loc[:, :2].max(axis=0) + 0.7
    ii, jj = np.mgrid[0:20:2, 0:30:2]
    x, y = jj * bank.dx[0] - bank.half[0, 0], ii * bank.dy[0] - bank.half[0, 1]
    inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1])
    assert len(rows) == inside.sum() > 0
    assert set(zip(rows.row.tolist(), rows.col.tolist(), strict=True)) == set(
        zip(ii[inside].tolist(), jj[inside].tolist(), strict=True)
    )
    # a point's height is its pixel's (smoothed) height, relative to the patch's median
    np.testing.assert_allclose(xyz[:, 2], bank.grid(0)[rows.row + 1, rows.col + 1])


def test_a_border_band_keeps_points_clear_of_both_borders_where_it_leaves_enough() -> None:
    # a overlaps b by 15 columns along x, c (below it) by 3 rows along y
    a = _plane_patch("a", (0.0, 0.0))
    b = _plane_patch("b", (150e-9, 0.0))
    c = _plane_patch("c", (0.0, 170e-9))
    bank = SurfaceBank([a, b, c], 10e-9, 1.0, 1, border="repeat")
    R = np.repeat(np.eye(3)[None], 3, axis=0)
    s = bank.centre.copy()
    pairs = np.array([[0, 1], [0, 2]])
    plain = bank.candidates(pairs, R, s, 1.5)
    banded = bank.candidates(pairs, R, s, 1.5, band=2.0)
    assert banded.src.tolist() == plain.src.tolist() and banded.dst.tolist() == plain.dst.tolist()
    rows = bank.rows(banded)
    for k, (src, dst) in enumerate(zip(banded.src, banded.dst, strict=True)):
        run = slice(banded.starts[k], banded.starts[k + 1])
        row, col = rows.row[run], rows.col[run]
        if {src, dst} == {0, 1}:  # 11 of the 15 columns, 16 of the 20 lines: two pixels clear
            assert set(row.tolist()) == set(range(2, 18))
            # of both borders: a's columns 17..27 (b's 2..12) and b's 2..12 (a's 17..27)
            assert set(col.tolist()) == set(range(17, 28) if src == 0 else range(2, 13))
        else:  # three lines of overlap keep too few of their points clear: all of them
            kept = bank.rows(plain, k, k + 1)
            assert row.tolist() == kept.row.tolist() and col.tolist() == kept.col.tolist()
    # a band that would leave a run under BAND_KEEPS of its points leaves it whole
    narrower = bank.candidates(pairs, R, s, 1.5, band=4.0)
    assert narrower.starts.tolist() == plain.starts.tolist()


def test_a_point_in_a_hole_gives_a_row_that_is_not_valid() -> None:
    p = _plane_patch("a", (0.0, 0.0))
    heights = p.heights.copy()
    heights[5, 25] = np.nan
    holed = Patch("a", heights, p.origin, p.pixel_size)
    bank = SurfaceBank([holed, _plane_patch("b", (200e-9, 0.0))], 10e-9, 0.0, 1)
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    state = PatchState(R, bank.centre.copy(), np.zeros((2, 2)))
    rows = bank.rows(bank.candidates(np.array([[0, 1]]), R, state.s, 0.0), 0, 1)
    _, ok, _, _ = residuals(bank, rows, state)
    # the spline through the pixels is not defined within a pixel of the hole
    near = (np.abs(rows.row - 5) <= 1) & (np.abs(rows.col - 25) <= 1)
    assert near.sum() == 9 and not ok[near].any() and ok[~near].all()
    assert bank.point_count.tolist() == [600 - 9, 600]


def test_narrow_nodes_and_rows_merge_as_float64_do(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the nodes' heights and the residuals are stored in float32, the rows' slopes in float16,
    # to save the mosaic's memory; the merge they give is the float64 one to a thousandth of a
    # nanometre
    narrow = run(small_mosaic.patch_set)
    monkeypatch.setattr(bank_module, "SURFACE_DTYPE", np.float64)
    monkeypatch.setattr(normal_system, "RESIDUAL_DTYPE", np.float64)
    monkeypatch.setattr(normal_system, "GRAD_DTYPE", np.float64)
    wide = run(small_mosaic.patch_set)
    assert narrow.iterations == wide.iterations
    patches = small_mosaic.patch_set.patches
    for a, b, p in zip(narrow.transforms, wide.transforms, patches, strict=True):
        np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-12)
        # a rotation by what it moves the patch's far corner
        reach = float(np.hypot(*np.multiply(p.shape[::-1], p.pixel_size)))
        np.testing.assert_allclose(a.R * reach, b.R * reach, rtol=0, atol=1e-12)
    np.testing.assert_allclose(narrow.mosaic.heights, wide.mosaic.heights, rtol=0, atol=1e-12)


def test_sharper_slopes_are_a_node_either_side_and_exact_on_a_plane() -> None:
    bank = SurfaceBank([_plane_patch("a", (0.0, 0.0))], 10e-9, 0.0, 1)
    pts = np.column_stack([np.linspace(-5.0, 5.0, 7), np.linspace(-3.0, 3.0, 7), np.zeros(7)])
    dst = np.zeros(len(pts), dtype=np.intp)
    _, gx, gy, ok = bank.lookup(dst, pts, reach=1)
    assert ok.all()
    np.testing.assert_allclose(gx, 0.3, atol=3e-6)
    np.testing.assert_allclose(gy, -0.2, atol=3e-6)
    for reach in (0, bank.nodes + 1):
        with pytest.raises(ValueError, match="reach"):
            bank.lookup(dst, pts, reach=reach)
