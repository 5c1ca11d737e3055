"""The coarse start's lattice images: common levelling, filled lines, texture, channels, and
what an overlap at a shift measures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from merge.core.downsample import GridSample
from merge.start.lattice import (
    coherence,
    correlated_channels,
    fill_empty_lines,
    overlap_information,
    overlap_measurement,
    overlap_z_difference,
    remove_common_plane,
    texture,
)


def _grid(heights: np.ndarray, x0: float = 0.0) -> GridSample:
    my, mx = heights.shape
    return GridSample(
        heights=heights,
        counts=np.ones(heights.shape, dtype=np.intp),
        x=(x0 + np.arange(mx) * 1e-8).astype(np.float64),
        y=(np.arange(my) * 1e-8).astype(np.float64),
        cell=1e-8,
    )


def test_one_sample_tilt_goes_and_each_patch_keeps_its_offset() -> None:
    yy, xx = np.mgrid[0:20, 0:30] * 1e-8
    tilt = 0.02 * xx - 0.01 * yy
    grids = [_grid(tilt[:, :20] + 50e-9), _grid(tilt[:, 10:] - 80e-9, x0=1e-7)]
    a, b = remove_common_plane(grids)
    assert np.ptp(a) == pytest.approx(0.0, abs=1e-15)
    assert np.ptp(b) == pytest.approx(0.0, abs=1e-15)
    assert float(a[0, 0] - b[0, 0]) == pytest.approx(130e-9, rel=1e-9)  # the staircase stays


def test_empty_lines_between_scan_lines_are_interpolated_and_holes_stay() -> None:
    h = np.tile(np.arange(8.0)[:, None], (1, 4))
    h[[1, 3], :] = np.nan  # lines no pixel fell in
    h[6, 2] = np.nan  # a hole within a sampled line
    filled = fill_empty_lines(_grid(h)).heights
    np.testing.assert_allclose(filled[[1, 3], :], [[1.0] * 4, [3.0] * 4])
    assert np.isnan(filled[6, 2]) and np.isfinite(np.delete(filled.ravel(), 6 * 4 + 2)).all()


def test_texture_is_what_is_left_about_the_patch_plane() -> None:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:40, 0:40].astype(np.float64)
    noise = rng.normal(0, 1.0, xx.shape)
    assert texture(3.0 * xx - 2.0 * yy + noise) == pytest.approx(noise.std(), rel=0.05)
    assert texture(np.full((1, 3), 1.0)) == 0.0  # too few points for a plane


def test_channels_are_heights_and_slopes_that_flatten_a_ramp() -> None:
    yy, xx = np.mgrid[0:12, 0:16].astype(np.float64)
    ch = correlated_channels(0.5 * xx + 0.25 * yy)
    assert ch.shape == (3, 12, 16)
    inner = (slice(4, -4), slice(4, -4))  # the smoothing holds the border's values
    np.testing.assert_allclose(ch[1][inner], 0.5, atol=1e-3)
    np.testing.assert_allclose(ch[2][inner], 0.25, atol=1e-3)


def _seen_at(a: np.ndarray, shift: tuple[int, int]) -> np.ndarray:
    """An image ``b`` of ``a``'s surface with ``b[y + dy, x + dx] = a[y, x]`` (NaN elsewhere)."""
    (dy, dx), (h, w) = shift, a.shape
    b = np.full(a.shape, np.nan)
    b[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = a[
        max(-dy, 0) : h - max(dy, 0), max(-dx, 0) : w - max(dx, 0)
    ]
    return b


def test_a_straight_edge_informs_across_it_only_and_texture_in_both_directions() -> None:
    rng = np.random.default_rng(0)
    cols = np.arange(40.0)
    edge = np.tile(50e-9 * np.tanh((cols - 20.0) / 2.0), (30, 1))  # an edge along y
    noisy = edge + rng.normal(0.0, 1e-9, edge.shape)
    seen = _seen_at(edge, (0, 5)) + rng.normal(0.0, 1e-9, edge.shape)
    info = overlap_information(noisy, seen, (0, 5), 1e-9, precision=0.1, aperture=0.01)
    vals, vecs = np.linalg.eigh(info)
    assert vals[1] == pytest.approx(100.0)  # capped at a tenth of a cell, across the edge
    assert abs(vecs[0, 1]) > 0.999
    assert abs(vals[0]) < 1e-9  # the aperture problem: nothing along it
    rough = rng.normal(0.0, 5e-9, (30, 40))
    both = overlap_information(
        rough, _seen_at(rough, (2, -3)), (2, -3), 1e-9, precision=0.1, aperture=0.01
    )
    assert np.linalg.eigvalsh(both).min() > 0
    # no overlap, or a one-line one, measures nothing
    assert not overlap_information(rough, rough, (30, 0), 1e-9, precision=0.1, aperture=0.01).any()
    assert not overlap_information(rough, rough, (29, 0), 1e-9, precision=0.1, aperture=0.01).any()


def test_roughness_beside_a_step_measures_along_it_and_noise_does_not() -> None:
    rng = np.random.default_rng(2)
    cols = np.arange(40.0)
    step = np.tile(500e-9 * np.tanh((cols - 20.0) / 2.0), (30, 1))  # a step along y
    rough = step + gaussian_filter(rng.normal(0.0, 4e-9, step.shape), 1.0)  # ~1.5 nm
    kw = {"precision": 0.1, "aperture": 0.01}
    noisy = rough + rng.normal(0.0, 0.5e-9, step.shape)
    seen = _seen_at(rough, (0, 5)) + rng.normal(0.0, 0.5e-9, step.shape)
    # the step holds far more than a hundred times the roughness's information...
    vals = np.linalg.eigvalsh(overlap_information(noisy, seen, (0, 5), 0.5e-9, **kw))
    assert abs(vals[0]) < 1e-9
    # ...yet the roughness measures the shift along it, well within a cell
    vals = np.linalg.eigvalsh(overlap_information(noisy, seen, (0, 5), 0.5e-9, texture=1.0, **kw))
    assert vals[0] >= 1.0 and vals[1] == pytest.approx(100.0)
    # at a shift along the step where the roughness does not agree, it measures nothing there
    # (overlaps a few cells wide: the correlation's ridge along a step rises with the overlap,
    # and from each image's own roughness its peak claimed the shift along the step, 240 nm
    # off); across the step the shift is still measured
    off = _seen_at(rough, (6, 5)) + rng.normal(0.0, 0.5e-9, step.shape)
    info = overlap_information(noisy, off, (0, 5), 0.5e-9, texture=1.0, **kw)
    assert info[1, 1] < 0.05 * vals[0] and info[0, 0] == pytest.approx(100.0)
    # a bare step under noise a fifth larger than estimated has no texture along it
    bare = step + rng.normal(0.0, 1.2e-9, step.shape)
    vals = np.linalg.eigvalsh(overlap_information(bare, bare, (0, 5), 1e-9, texture=1.0, **kw))
    assert abs(vals[0]) < 1e-9


def test_the_z_difference_is_the_median_over_the_overlap_at_the_shift() -> None:
    a = np.arange(20.0).reshape(4, 5)
    b = np.full((4, 5), np.nan)
    b[1:, 2:] = a[:3, :3] + 7.0  # b[y + 1, x + 2] = a[y, x] + 7
    b[3, 4] = 1e9  # an outlier the median ignores
    assert overlap_z_difference(a, b, (1, 2)) == (7.0, 9)
    assert overlap_z_difference(a, b, (4, 0)) == (pytest.approx(np.nan, nan_ok=True), 0)


def test_coherence_tells_stripes_from_roughness() -> None:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:60, 0:60].astype(float)
    stripes = np.sin(2 * np.pi * (xx + yy) / 15.0) + 0.05 * rng.normal(size=xx.shape)
    assert coherence(stripes) > 0.95
    rough = gaussian_filter(rng.normal(size=xx.shape), 1.5)
    assert coherence(rough) < 0.3
    # a tilt is not structure, and nothing is nothing
    assert coherence(0.3 * xx + 0.1 * yy) == 0.0
    stripes[:, :20] = np.nan
    assert coherence(stripes) > 0.95


def test_an_edge_only_one_image_holds_in_the_overlap_measures_nothing() -> None:
    # image a has a second edge across the rows of the overlap that image b does not hold
    # there (the shift is wrong): from a alone the overlap claimed the shift along the first
    rng = np.random.default_rng(3)
    cols, rows = np.arange(30.0), np.arange(20.0)
    along_y = np.tile(300e-9 * np.tanh((cols - 15.0) / 2.0), (20, 1))
    a = along_y + np.tanh((rows[:, None] - 2.0) / 1.0) * 300e-9
    b = along_y.copy()
    a, b = (x + rng.normal(0.0, 1e-9, x.shape) for x in (a, b))
    kw = {"precision": 0.1, "aperture": 0.01}
    one_sided = overlap_information(a, a, (0, 0), 1e-9, **kw)
    assert np.linalg.eigvalsh(one_sided).min() > 1.0  # a alone: both directions
    info = overlap_information(a, b, (0, 0), 1e-9, **kw)
    assert info[1, 1] < 1e-3 and info[0, 0] == pytest.approx(100.0)  # nothing along y
    edge = overlap_measurement(a, b, (0, 0), 1e-9, **kw)[1]
    assert edge is not None and abs(edge[1]) == pytest.approx(1.0, abs=1e-3)  # along y


def test_structure_both_ways_or_none_has_no_edge_direction() -> None:
    rng = np.random.default_rng(4)
    rough = gaussian_filter(rng.normal(0.0, 5e-9, (30, 40)), 1.0)
    kw = {"precision": 0.1, "aperture": 0.01}
    assert overlap_measurement(rough, rough, (1, 2), 1e-10, **kw)[1] is None
    flat = rng.normal(0.0, 1e-9, (30, 40))
    assert overlap_measurement(flat, flat, (1, 2), 1e-9, **kw)[1] is None


def test_a_slope_the_whole_overlap_shares_measures_no_shift_along_it() -> None:
    # a ramp wider than the overlap (a chessboard's 300 nm edges in strips of a few cells):
    # shifted along it, the overlap only rises, which its Z offset takes
    rng = np.random.default_rng(6)
    cols = np.arange(40.0)
    ramp = np.tile(2e-9 * cols, (30, 1))
    a = ramp + rng.normal(0.0, 0.5e-9, ramp.shape)
    b = _seen_at(ramp, (0, 5)) + rng.normal(0.0, 0.5e-9, ramp.shape)
    info = overlap_information(a, b, (0, 5), 0.5e-9, precision=0.1, aperture=0.01)
    assert np.abs(info).max() < 1.0  # nothing near the cap of 100 per cell²
