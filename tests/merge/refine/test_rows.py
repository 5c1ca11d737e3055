"""Correspondence rows: residuals that move every point as its patch says, exact run sums."""

from __future__ import annotations

import numpy as np

from merge.core.patchset import Patch
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState, lever_arms, residuals, segment_sums


def test_segment_sums_equal_the_sums_they_stand_for() -> None:
    rng = np.random.default_rng(3)
    J, w, r = rng.normal(size=(50, 6)), rng.uniform(0, 2, 50), rng.normal(size=50)
    starts = np.array([0, 7, 8, 30, 50])
    B, g = segment_sums(J, w, r, starts)
    for k in range(4):
        sl = slice(starts[k], starts[k + 1])
        np.testing.assert_allclose(B[k], (J[sl] * w[sl, None]).T @ J[sl], atol=1e-12)
        np.testing.assert_allclose(g[k], (w[sl] * r[sl]) @ J[sl], atol=1e-12)


def four_patches() -> tuple[SurfaceBank, PatchState]:
    """Four textured 24 x 24 patches in a square, each a little rotated and off (pixel units)."""
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:24, 0:24].astype(np.float64)
    patches = []
    for k, (x0, y0) in enumerate([(0.0, 0.0), (160e-9, 0.0), (0.0, 160e-9), (160e-9, 160e-9)]):
        x, y = xx * 10e-9 + x0, yy * 10e-9 + y0
        h = 20e-9 * np.sin(x / 70e-9) * np.cos(y / 90e-9) + rng.normal(0, 1e-9, x.shape)
        patches.append(Patch(id=str(k), heights=h, origin=(x0, y0), pixel_size=(10e-9, 10e-9)))
    bank = SurfaceBank(patches, 10e-9, 0.0, 1)
    angle = rng.normal(0, 0.01, 4)
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((4, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    state = PatchState(R, bank.centre + rng.normal(0, 0.3, (4, 3)), rng.normal(0, 1e-3, (4, 2)))
    return bank, state


def test_residuals_move_every_point_as_its_patch_state_says() -> None:
    bank, state = four_patches()
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    rows = bank.rows(bank.candidates(pairs, state.R, state.s, 1.5))
    src, dst = rows.src, rows.dst
    r, valid, _, _ = residuals(bank, rows, state)
    p = bank.point_xyz(rows)
    arm = lever_arms(p, rows, state)
    # row by row: into the mosaic with the source's state, back out with the destination's
    rot = np.einsum("mij,mj->mi", state.R[src], p)
    q = rot + state.s[src]
    q[:, 2] += np.einsum("mi,mi->m", state.slope[src], p[:, :2])
    p_dst = np.einsum("mji,mj->mi", state.R[dst], q - state.s[dst])
    h, _, _, ok = bank.lookup(dst, p_dst)
    expected = p_dst[:, 2] - np.einsum("mi,mi->m", state.slope[dst], p_dst[:, :2]) - h
    assert ok.sum() > 0.5 * len(ok)
    np.testing.assert_array_equal(valid, ok)
    np.testing.assert_allclose(r[ok], expected[ok], atol=1e-9)
    np.testing.assert_allclose(arm, rot[:, :2], atol=1e-12)


def side_by_side(noise: float, seed: int) -> tuple[SurfaceBank, PatchState]:
    """Two flat 48 x 256 px patches of white noise, 12 px of overlap, at their true places."""
    rng = np.random.default_rng(seed)
    patches = [
        Patch(
            id=str(k),
            heights=rng.normal(0.0, noise, (256, 48)),
            origin=(k * 36.0, 0.0),
            pixel_size=(1.0, 1.0),
        )
        for k in range(2)
    ]
    bank = SurfaceBank(patches, 1.0, 0.0, 1)
    R = np.repeat(np.eye(3)[None], 2, axis=0)
    return bank, PatchState(R, bank.centre.copy(), np.zeros((2, 2)))


def test_slopes_at_the_destination_border_share_no_noise_with_the_residual() -> None:
    # a slope correlated with its residual biases every step: within a pixel of the border the
    # destination's own (one-sided, from the border pixels) are; the source's are not
    used, own = [], []
    for seed in range(4):
        bank, state = side_by_side(1.0, seed)
        rows = bank.rows(bank.candidates(np.array([[0, 1]]), state.R, state.s, 1.5))
        r, ok, grad, _ = residuals(bank, rows, state)
        # the patches are not turned: a point's place on the other is its offset away
        p = bank.point_xyz(rows) + state.s[rows.src] - state.s[rows.dst]
        near = ok & bank.near_border(rows.dst, p)
        _, gx, _, _ = bank.lookup(rows.dst, p)
        # both ways of the pair push its shift together: the other way's score counts negated
        way = np.where(rows.src == 0, 1.0, -1.0)[near]
        used.append(way * grad[near, 0] * r[near])
        own.append(way * gx[near] * r[near])
    u, o = np.concatenate(used), np.concatenate(own)
    err = o.std() / np.sqrt(len(o))
    assert len(o) > 1000
    assert abs(o.mean()) > 6 * err  # the problem: the destination's slopes carry the bias
    assert abs(u.mean()) < 3 * u.std() / np.sqrt(len(u))


def test_a_points_own_slopes_are_three_lines_central_differences_free_of_its_noise() -> None:
    bank, state = side_by_side(1.0, 5)
    rows = bank.rows(bank.candidates(np.array([[0, 1]]), state.R, state.s, 1.5))
    g = bank.point_slopes(rows, np.arange(len(rows.src)))
    h = bank.point_xyz(rows)[:, 2]
    border = (rows.row == 0) | (rows.col == 0) | (rows.row == 255) | (rows.col == 47)
    assert np.isnan(g[border]).all() and np.isfinite(g[~border]).all()
    g, h = g[~border], h[~border]
    # unit white noise: 3/16 per pitch² averaged over three lines (a lone central difference:
    # 1/2), and none of it shared with the point's own height
    np.testing.assert_allclose(g.var(axis=0), 3 / 16, rtol=0.15)
    for k in range(2):
        score = g[:, k] * h
        assert abs(score.mean()) < 4 * score.std() / np.sqrt(len(score))
    # on a plane, its slopes
    plane = 0.3 * np.arange(48.0) - 0.2 * np.arange(256.0)[:, None]
    tilted = [Patch(str(k), plane, (k * 36.0, 0.0), (1.0, 1.0)) for k in range(2)]
    slopes = SurfaceBank(tilted, 1.0, 0.0, 1).point_slopes(rows, np.flatnonzero(~border))
    np.testing.assert_allclose(slopes, np.tile([0.3, -0.2], (len(slopes), 1)), atol=1e-5)
