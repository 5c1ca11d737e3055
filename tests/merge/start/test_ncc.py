import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from merge.start import ncc as ncc_module
from merge.start.ncc import _Lattice, best_shift, chunk_size, masked_ncc, pair_maps


def texture(seed: int, shape: tuple[int, int] = (60, 60)) -> np.ndarray:
    out: np.ndarray = gaussian_filter(np.random.default_rng(seed).normal(size=shape), 2)
    return out


def test_finds_the_shift_whatever_the_offset_and_gain() -> None:
    big = texture(1, (80, 80))
    a = big[10:50, 10:50]
    b = 3.0 * big[14:54, 7:47] + 100.0  # b[y, x] = a[y + 4, x - 3]: shift (-4, 3)
    peak = best_shift(a, b, min_overlap=200)
    assert peak is not None
    assert peak.integer_shift == (-4, 3)
    assert peak.score == pytest.approx(1.0, abs=1e-6)
    assert peak.overlap == 36 * 37


def test_missing_pixels_do_not_bias_the_score() -> None:
    big = texture(2, (80, 80))
    a = big[10:50, 10:50].copy()
    b = big[12:52, 10:50].copy()
    a[5:15, 5:15] = np.nan
    b[20:30, :] = np.nan
    peak = best_shift(a, b, min_overlap=100)
    assert peak is not None and peak.integer_shift == (-2, 0)


def test_radius_limits_the_search_and_flags_the_border() -> None:
    big = texture(3, (80, 80))
    a, b = big[10:50, 10:50], big[18:58, 10:50]  # true shift (-8, 0)
    peak = best_shift(a, b, expected=(0, 0), radius=(3, 3), min_overlap=100)
    assert peak is not None and peak.at_border


def test_channels_are_averaged() -> None:
    a = texture(4, (30, 30))
    ncc, count, zero = masked_ncc(np.stack([a, a]), np.stack([a, -a]), weights=[1, 1])
    assert ncc[zero] == pytest.approx(0.0, abs=1e-9)
    assert count[zero] == 900
    with pytest.raises(ValueError, match="channel"):
        masked_ncc(np.stack([a, a]), a[None])


def test_pair_maps_score_every_pair_as_alone() -> None:
    # images of two shapes, holes, channels of very different scales: each image transformed
    # once for all its pairs gives every pair's map as masked_ncc gives it alone
    big = texture(5, (90, 90))
    images = []
    for k, (h, w) in enumerate([(30, 40), (30, 40), (24, 40), (30, 40)]):
        y, x = 3 * k, 2 * k
        stack = np.stack([100.0 * big[y : y + h, x : x + w], big[x : x + h, y : y + w] - 5.0])
        stack[:, k : k + 4, 10:20] = np.nan
        images.append(stack)
    pairs = np.array([[0, 1], [1, 2], [2, 3], [0, 3], [3, 1], [2, 0]])
    weights = [0.7, 0.3]
    for i, ncc, count, zero in pair_maps(images, pairs, range(len(pairs)), weights=weights):
        alone, alone_count, alone_zero = masked_ncc(*(images[c] for c in pairs[i]), weights=weights)
        used = alone_count >= 16
        assert zero == alone_zero
        np.testing.assert_array_equal(count, alone_count)
        np.testing.assert_allclose(ncc[used], alone[used], atol=1e-4)


def test_pair_maps_in_chunks_equal_them_at_once(monkeypatch: pytest.MonkeyPatch) -> None:
    # the spectra of a large mosaic's images are taken a few hundred pairs at a time: the maps
    # are the same however the pairs are cut
    big = texture(6, (90, 90))
    images = [big[3 * k : 3 * k + 30, 2 * k : 2 * k + 40] for k in range(6)]
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5], [0, 5], [1, 4]])
    whole = {i: (m, c) for i, m, c, _ in pair_maps(images, pairs, range(len(pairs)))}
    monkeypatch.setattr(ncc_module, "SPECTRA_PAIRS", 2)
    for batch in (None, 1, 3):  # maps computed so many pairs at a time
        for i, m, c, _ in pair_maps(images, pairs, range(len(pairs)), batch=batch):
            np.testing.assert_array_equal(c, whole[i][1])
            np.testing.assert_allclose(m, whole[i][0], atol=1e-9)


def test_few_pairs_are_taken_in_smaller_chunks() -> None:
    # a small mosaic's working set is a share of its data; a large one's is capped
    assert chunk_size(360, ncc_module.SPECTRA_SHARE, ncc_module.SPECTRA_PAIRS, 16) == 30
    assert chunk_size(360, ncc_module.MAP_SHARE, ncc_module.MAP_BATCH, 4) == 4
    assert chunk_size(40, ncc_module.SPECTRA_SHARE, ncc_module.SPECTRA_PAIRS, 16) == 16
    big = chunk_size(60_000, ncc_module.SPECTRA_SHARE, ncc_module.SPECTRA_PAIRS, 16)
    assert big == ncc_module.SPECTRA_PAIRS


def test_full_images_score_by_summed_areas_as_by_masks() -> None:
    # no missing pixel: overlap sums come from summed-area tables, not from transforms; every
    # shift of two images of different shapes scores as the masked path scores it
    big = texture(8, (90, 90))
    a = np.stack([big[10:40, 5:45], 50.0 * big[40:70, 20:60] + 3.0])[None]
    b = np.stack([big[14:40, 9:42], 50.0 * big[44:70, 24:57] + 3.0])[None]
    lattice, w = _Lattice.of(a.shape, b.shape), np.array([0.6, 0.4])
    dense, dense_count = lattice.ncc(
        lattice.spectra(a, first=True, dense=True), lattice.spectra(b, first=False, dense=True), w
    )
    masked, masked_count = lattice.ncc(
        lattice.spectra(a, first=True), lattice.spectra(b, first=False), w
    )
    np.testing.assert_array_equal(dense_count, masked_count)
    used = dense_count >= 16
    np.testing.assert_allclose(dense[used], masked[used], atol=1e-4)
    # and the true shift wins: b[y + dy, x + dx] = a[y, x] with (dy, dx) = (-4, -4)
    k = np.unravel_index(np.nanargmax(np.where(used, dense, np.nan)), dense.shape)
    assert (k[1] - lattice.zero[0], k[2] - lattice.zero[1]) == (-4, -4)
    with pytest.raises(ValueError, match="missing pixels"):
        lattice.spectra(np.where(a > 1.0, np.nan, a), first=True, dense=True)


def _grating(shift: int, noise_seed: int) -> np.ndarray:
    # stripes with a period of 10 px along x on a texture that varies along y only: the NCC
    # peak is unique along y and repeats every 10 px along x, nearly equal
    x = np.arange(60)[None, :] + shift
    rows = gaussian_filter(np.random.default_rng(0).normal(size=40), 2)[:, None]
    noise = np.random.default_rng(noise_seed).normal(0, 0.05, (40, 60))
    out: np.ndarray = np.sin(2 * np.pi * x / 10.0) + 3.0 * rows + noise
    return out


@pytest.mark.parametrize(("expected_dx", "chosen_dx"), [(1.0, 3), (11.0, 13), (-9.0, -7)])
def test_among_peaks_a_period_apart_the_one_nearest_the_expected_shift_wins(
    expected_dx: float, chosen_dx: int
) -> None:
    # b[y, x] = a[y, x + 3]: the true shift is 3 px, and 3 +- 10 k look the same
    a, b = _grating(3, 1), _grating(0, 2)
    peak = best_shift(a, b, expected=(0.0, expected_dx), min_overlap=200, ambiguity=0.1)
    assert peak is not None
    assert peak.integer_shift == (0, chosen_dx)


def test_a_unique_peak_wins_however_far_from_the_expected_shift() -> None:
    big = texture(4, (90, 90))
    a = big[10:50, 10:50]
    b = big[4:44, 19:59]  # shift (6, -9)
    peak = best_shift(a, b, expected=(0.0, 0.0), min_overlap=200, ambiguity=0.1)
    assert peak is not None
    assert peak.integer_shift == (6, -9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_weak_true_peak_stands_out_of_chance_and_a_chance_peak_does_not(seed: int) -> None:
    # texture as fine as a pixel under twice its noise: the true peak scores only ~0.2, but
    # chance scores over ~3000 pixels spread by ~0.02
    rng = np.random.default_rng(seed)
    common = rng.normal(size=(70, 70))
    a = common[5:65, 5:65] + 2.0 * rng.normal(size=(60, 60))
    b = common[8:68, 3:63] + 2.0 * rng.normal(size=(60, 60))
    peak = best_shift(a, b, radius=(8, 8), min_overlap=400)
    assert peak is not None and peak.integer_shift == (-3, 2)
    assert peak.score < 0.3 and peak.excess > 3.0
    other = rng.normal(size=(60, 60))
    chance = best_shift(a, other, radius=(8, 8), min_overlap=400)
    assert chance is not None and chance.excess < 3.0


def test_peaks_a_period_apart_are_not_one_ridge() -> None:
    # alike peaks a period apart have a valley between them: the chosen one has no alike
    # neighbours on its own ridge, and its shift is measured both ways
    a, b = _grating(3, 1), _grating(0, 2)
    periodic = best_shift(a, b, expected=(0.0, 0.0), min_overlap=200, ambiguity=0.1)
    assert periodic is not None and periodic.ridge == ()
