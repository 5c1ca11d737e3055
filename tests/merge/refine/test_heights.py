"""The heights' last solve: Z offsets, drift planes and every scan line's offset at once."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from merge.core.overlap import overlapping_pairs
from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform
from merge.refine.heights import PairRows, line_statistics, line_weights, pair_rows, solve_heights

PIXEL = 10e-9
SIDE = 48
STEP = 36  # pixels between neighbours: overlaps of 12 px
TAU = 0.5e-9
NOISE = 0.2e-9


def _surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth rough surface (metres): a few waves, some tens of nm long."""
    out = np.zeros_like(x)
    rng = np.random.default_rng(7)
    for _ in range(12):
        k = rng.uniform(2 * np.pi / 300e-9, 2 * np.pi / 60e-9) * np.array(
            [np.cos(a := rng.uniform(0, np.pi)), np.sin(a)]
        )
        out += 2e-9 * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 2 * np.pi))
    return out


def _mosaic(
    tau: float = TAU, seed: int = 0
) -> tuple[list[Patch], list[PatchTransform], np.ndarray, list[np.ndarray]]:
    """A 3 x 3 mosaic scanned with Z offsets, line offsets (``tau``) and white noise; its true
    transforms, the Z offsets and every patch's line offsets."""
    rng = np.random.default_rng(seed)
    patches, truth, lines = [], [], []
    offsets = rng.normal(0.0, 20e-9, 9)
    for k in range(9):
        origin = ((k % 3) * STEP * PIXEL, (k // 3) * STEP * PIXEL)
        yy, xx = np.mgrid[0:SIDE, 0:SIDE]
        h = _surface(origin[0] + xx * PIXEL, origin[1] + yy * PIXEL)
        c = rng.normal(0.0, tau, SIDE)
        h = h + offsets[k] + c[:, None] + rng.normal(0.0, NOISE, h.shape)
        patches.append(Patch(f"p{k}", h, origin, (PIXEL, PIXEL)))
        centre = np.array(origin) + 0.5 * (SIDE - 1) * PIXEL
        truth.append(PatchTransform(t=np.array([0.0, 0.0, -offsets[k]]), centre=centre))
        lines.append(c)
    return patches, truth, offsets, lines


def _pairs(patches: list[Patch]) -> np.ndarray:
    boxes = np.array(
        [[*p.origin, p.origin[0] + SIDE * PIXEL, p.origin[1] + SIDE * PIXEL] for p in patches]
    )
    return overlapping_pairs(boxes)


def _height_errors(
    patches: list[Patch], placed: list[PatchTransform], truth: list[PatchTransform]
) -> np.ndarray:
    """(9,) RMS over every patch's pixels of its placed heights against the true ones, the
    common offset taken out."""
    per = []
    for p, T, U in zip(patches, placed, truth, strict=True):
        yy, xx = np.mgrid[0:SIDE, 0:SIDE]
        pts = np.column_stack(
            [p.origin[0] + xx.ravel() * PIXEL, p.origin[1] + yy.ravel() * PIXEL, np.zeros(xx.size)]
        )
        per.append(T.apply(pts)[:, 2] - U.apply(pts)[:, 2])
    e = np.array(per)
    e -= e.mean()
    return np.sqrt(np.mean(e**2, axis=1))


def _disturbed(truth: list[PatchTransform], seed: int = 1) -> list[PatchTransform]:
    """The true transforms with every patch's Z (1 nm) and drift plane (1 nm at its edge) off."""
    rng = np.random.default_rng(seed)
    out = []
    for T in truth:
        t = T.t.copy()
        t[2] += rng.normal(0.0, 1e-9)
        slope = rng.normal(0.0, 1e-9 / (0.5 * SIDE * PIXEL), 2)
        out.append(PatchTransform(T.R, t, slope, T.centre))
    return out


def test_the_heights_and_the_lines_offsets_are_recovered() -> None:
    patches, truth, _, lines = _mosaic()
    start = _disturbed(truth)
    before = _height_errors(patches, start, truth)
    solved = solve_heights(patches, start, _pairs(patches), plane_sigma=(2e-9, 2e-9))
    assert solved is not None
    after = _height_errors(patches, solved.transforms, truth)
    # from over a nanometre to a fifth of one (the lines leave every patch a ramp's doubt)
    assert np.sqrt(np.mean(before**2)) > 1e-9
    assert np.sqrt(np.mean(after**2)) < 0.25 * np.sqrt(np.mean(before**2))
    # the lines' sigma as drawn (0.5 nm), and the offsets themselves, each patch's ramp and
    # mean aside (a patch's Z and plane trade with them)
    assert solved.statistics.tau == pytest.approx(TAU, rel=0.25)
    y = np.arange(SIDE) - 0.5 * (SIDE - 1)
    X = np.column_stack([np.ones(SIDE), y])

    def detrended(c: np.ndarray) -> np.ndarray:
        return c - X @ np.linalg.lstsq(X, c, rcond=None)[0]

    found = np.concatenate([detrended(c) for c in solved.line_offsets])
    drawn = np.concatenate([detrended(c) for c in lines])
    assert np.corrcoef(found, drawn)[0, 1] > 0.75


@pytest.mark.parametrize("tau", [0.0, 0.01e-9])
def test_scans_whose_lines_offsets_do_not_stand_out_are_left_as_they_are(tau: float) -> None:
    # none at all, or less than the noise of a line's mean over the overlap: the refinement's
    # random effects told as much
    patches, truth, _, _ = _mosaic(tau=tau)
    assert (
        solve_heights(patches, _disturbed(truth), _pairs(patches), plane_sigma=(2e-9, 2e-9)) is None
    )


def test_bad_input_is_refused() -> None:
    patches, truth, _, _ = _mosaic()
    pairs = _pairs(patches)
    with pytest.raises(ValueError, match="one transform per patch"):
        solve_heights(patches, truth[:-1], pairs, plane_sigma=(1e-9, 1e-9))
    with pytest.raises(ValueError, match="plane_sigma"):
        solve_heights(patches, truth, pairs, plane_sigma=(0.0, 1e-9))
    assert (
        solve_heights(patches, truth, np.empty((0, 2), dtype=np.intp), plane_sigma=(1e-9, 1e-9))
        is None
    )


def test_a_pair_reads_the_other_patch_where_it_lies() -> None:
    # at the true places the residuals are the two scans' line offsets and noise, nothing else
    patches, truth, _, lines = _mosaic()
    rows = pair_rows(patches[0], patches[1], truth[0], truth[1])
    assert rows is not None
    assert np.all(rows.line >= 0) and np.all(rows.line < SIDE)
    expected = lines[0][rows.line] - (
        (1 - rows.f) * lines[1][rows.j] + rows.f * lines[1][rows.j + 1]
    )
    assert np.std(rows.r - expected) < 4 * NOISE
    # patches that do not meet have no rows
    assert pair_rows(patches[0], patches[8], truth[0], truth[8]) is None


def test_the_lines_sigma_is_measured_from_the_rows() -> None:
    patches, truth, _, _ = _mosaic(seed=3)
    pairs = _pairs(patches)
    rows = [pair_rows(patches[a], patches[b], truth[a], truth[b]) for a, b in pairs.tolist()]
    kept = [r for r in rows if r is not None]
    stats = line_statistics(kept, [(NOISE, NOISE)] * len(kept))
    assert stats.tau == pytest.approx(TAU, rel=0.25)
    assert stats.noise == pytest.approx(NOISE * np.sqrt(1.5), rel=0.3)
    # no rows, no statistics
    assert line_statistics([]).tau == 0.0


@settings(max_examples=30, deadline=None)
@given(
    shift=st.floats(-50e-9, 50e-9),
    line=st.integers(0, 9),
    seed=st.integers(0, 2**16),
)
def test_a_lines_offset_does_not_change_the_weights(shift: float, line: int, seed: int) -> None:
    # robust weights taken on the residuals themselves would shrink the lines with large
    # offsets; taken on the deviations from their line's mean, they do not see them
    rng = np.random.default_rng(seed)
    m = 200
    at = np.repeat(np.arange(10), m // 10)
    r = rng.normal(0.0, 1e-9, m)
    r[5] += 30e-9  # an outlier
    rows = PairRows(r, at, at, np.zeros(m), np.zeros((m, 2)), np.zeros((m, 2)))
    moved = PairRows(
        r + shift * (at == line), at, at, np.zeros(m), np.zeros((m, 2)), np.zeros((m, 2))
    )
    w0, w1 = line_weights(rows, 1e-9), line_weights(moved, 1e-9)
    np.testing.assert_allclose(w1, w0, rtol=1e-6, atol=1e-9)
    assert w0[5] < 0.05


def test_the_refinement_of_a_whole_mosaic_ends_with_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # refine() hands the whole mosaic's placement to the heights' solve and returns its
    # transforms; with patches held (a live merge's neighbourhood) it does not run
    from merge.refine import icp

    patches, truth, _, _ = _mosaic()
    calls: list[int] = []

    def spy(*args: object, **kwargs: object) -> object:
        out = solve_heights(*args, **kwargs)  # type: ignore[arg-type]
        calls.append(1)
        return out

    monkeypatch.setattr(icp, "solve_heights", spy)
    pairs = _pairs(patches)
    result = icp.refine(patches, pairs, _disturbed(truth))
    assert calls == [1]
    assert np.sqrt(np.mean(_height_errors(patches, result.transforms, truth) ** 2)) < 0.3e-9
    held = np.zeros(len(patches), dtype=bool)
    held[0] = True
    icp.refine(patches, pairs, _disturbed(truth), held=held)
    assert calls == [1]


def test_noise_free_scans_and_missing_pixels_are_handled() -> None:
    # nothing to weigh the rows by without noise: left as they are, not divided by zero
    patches, truth, _, _ = _mosaic()
    clean = [Patch(p.id, np.zeros_like(p.heights), p.origin, p.pixel_size) for p in patches]
    assert solve_heights(clean, truth, _pairs(clean), plane_sigma=(2e-9, 2e-9)) is None
    # a scan with missing pixels (NaN) is read where it was measured
    holed = [Patch(p.id, p.heights.copy(), p.origin, p.pixel_size) for p in patches]
    for p in holed:
        p.heights[10:20, 5:40] = np.nan
    solved = solve_heights(holed, _disturbed(truth), _pairs(holed), plane_sigma=(2e-9, 2e-9))
    assert solved is not None
    assert all(np.all(np.isfinite(T.t)) and np.all(np.isfinite(T.slope)) for T in solved.transforms)
