"""Masked normalized cross-correlation of two images for all integer shifts (Padfield 2012).

Each shift is scored only on the pixels both images hold there, with means and variances taken
over that overlap: so a Z offset between the images, NaN holes and partial overlap do not bias
the score. Sums over the overlaps are correlations with the masks, done by FFT; between images
without holes every overlap is a rectangle, and summed-area tables give those sums instead,
leaving one transform per channel (the cross term) where the masks took five.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import fft

from merge.start.peaks import CorrelationPeak, find_peak

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


def masked_ncc(
    a: FloatArray, b: FloatArray, *, weights: Sequence[float] | None = None
) -> tuple[FloatArray, FloatArray, tuple[int, int]]:
    """NCC and overlap count for every shift, averaged over channels; batches allowed.

    Parameters
    ----------
    a, b : (h, w), (channels, h, w) or (batch, channels, h, w) arrays
        Images (or stacks of channels of the same images, e.g. heights and slopes), or a batch
        of such image pairs of equal shapes; NaN marks missing pixels. A pixel counts where
        every channel of its image is finite.
    weights : sequence of float, keyword-only
        Weight of every channel in the average (default equal).

    Returns
    -------
    ncc : ([batch,] ha + hb - 1, wa + wb - 1) array
        ``ncc[..., k, l]`` scores the shift ``(k - (ha - 1), l - (wa - 1))``; NaN where undefined.
    count : same shape
        Number of overlapping valid pixels.
    zero : (ha - 1, wa - 1)
        Index of the zero shift.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    single = a.ndim <= 3
    a = a.reshape((1,) * (4 - a.ndim) + a.shape) if a.ndim < 4 else a
    b = b.reshape((1,) * (4 - b.ndim) + b.shape) if b.ndim < 4 else b
    if a.ndim != 4 or b.ndim != 4 or a.shape[:2] != b.shape[:2]:
        raise ValueError("masked_ncc needs two images (or stacks with the same channel count)")
    w = _channel_weights(weights, a.shape[1])
    lattice = _Lattice.of(a.shape[-2:], b.shape[-2:])
    dense = bool(np.isfinite(a).all() and np.isfinite(b).all())
    ncc, count = lattice.ncc(
        lattice.spectra(a, first=True, dense=dense), lattice.spectra(b, first=False, dense=dense), w
    )
    if single:
        return ncc[0], count[0], lattice.zero
    return ncc, count, lattice.zero


#: Pairs whose images are transformed together in :func:`pair_maps` (their spectra held at once:
#: with 512, 40 bytes per input pixel of 100 patches of 64 x 64 px), at most.
SPECTRA_PAIRS = 128
#: Pairs whose NCC maps :func:`pair_maps` computes together, at most (64 pairs: 180 bytes per
#: input pixel of 100 patches of 64 x 64 px; 16: 64, as fast within the spread of the timings).
MAP_BATCH = 16
#: Share of all pairs in one chunk of either kind: a small mosaic's chunks are smaller than the
#: caps above, so its working set stays a share of its data (100 patches of 64 x 64 px: 30 and
#: 4 pairs, the coarse start's peak 30 -> 16 MB, 74 -> 40 bytes per input pixel; 400 patches
#: reach the caps).
SPECTRA_SHARE, MAP_SHARE = 1 / 12, 1 / 96


def chunk_size(pairs: int, share: float, cap: int, least: int) -> int:
    """Pairs of ``pairs`` to take at a time: ``share`` of them, within ``[least, cap]``."""
    return int(np.clip(int(pairs * share), least, cap))


def _channel_weights(weights: Sequence[float] | None, channels: int) -> FloatArray:
    w = np.ones(channels) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (channels,) or (w < 0).any() or w.sum() <= 0:
        raise ValueError("weights must be one non-negative number per channel")
    out: FloatArray = w / w.sum()
    return out


@dataclass(frozen=True)
class _Spectra:
    """Fourier transforms of a batch of channel stacks on one padded lattice: per channel the
    standardised values (batch, C, H, W'), and either the masks (batch, H, W') and the values'
    squares (batch, C, H, W') or, for images without missing pixels, summed-area tables of the
    values and their squares (batch, C, h + 1, w + 1): over a full image every overlap is a
    rectangle, and its sums are four look-ups instead of four transforms. An image's spectra
    serve every pair it is in."""

    values: NDArray[np.complex64]
    mask: NDArray[np.complex64] | None = None
    squares: NDArray[np.complex64] | None = None
    sums: FloatArray | None = None
    sums2: FloatArray | None = None

    @property
    def dense(self) -> bool:
        return self.sums is not None

    def take(self, index: IntArray) -> _Spectra:
        def pick(x: NDArray[Any] | None) -> NDArray[Any] | None:
            return None if x is None else x[index]

        return _Spectra(
            self.values[index],
            pick(self.mask),
            pick(self.squares),
            pick(self.sums),
            pick(self.sums2),
        )


def _summed_area(x: FloatArray) -> FloatArray:
    """Summed-area table (..., h + 1, w + 1) of ``x`` (..., h, w): ``[i, j]`` sums ``x[:i, :j]``."""
    out = np.zeros((*x.shape[:-2], x.shape[-2] + 1, x.shape[-1] + 1))
    out[..., 1:, 1:] = x.cumsum(axis=-2).cumsum(axis=-1)
    return out


def _box(
    table: FloatArray, rows: tuple[IntArray, IntArray], cols: tuple[IntArray, IntArray]
) -> FloatArray:
    """Sums of rectangles ``rows[0][k]:rows[1][k]`` x ``cols[0][l]:cols[1][l]`` from a summed-area
    table (..., h + 1, w + 1): (..., len(rows[0]), len(cols[0])). Rows, then columns, one
    difference of two whole-axis gathers each."""
    strips = np.take(table, rows[1], axis=-2) - np.take(table, rows[0], axis=-2)
    out: FloatArray = np.take(strips, cols[1], axis=-1) - np.take(strips, cols[0], axis=-1)
    return out


@dataclass(frozen=True)
class _Lattice:
    """The padded FFT lattice of image pairs of shapes ``a`` and ``b`` (Padfield's method)."""

    a: tuple[int, int]
    b: tuple[int, int]
    shape: tuple[int, int]

    @classmethod
    def of(cls, a: tuple[int, ...], b: tuple[int, ...]) -> _Lattice:
        ha, wa = int(a[-2]), int(a[-1])
        hb, wb = int(b[-2]), int(b[-1])
        shape = (
            fft.next_fast_len(ha + hb - 1, real=True),
            fft.next_fast_len(wa + wb - 1, real=True),
        )
        return cls((ha, wa), (hb, wb), shape)

    @property
    def zero(self) -> tuple[int, int]:
        return self.a[0] - 1, self.a[1] - 1

    def _fft(self, x: NDArray[np.float64] | NDArray[np.bool_]) -> NDArray[np.complex64]:
        # Single precision halves the memory traffic of this, the start's costliest step:
        # inputs are standardised, so sums stay far from float32's limits, and the scores need
        # ~1e-4 at most (the refinement, in double precision, measures the sub-pixel shift).
        # One thread: the batches are small (16 pairs' maps), and pocketfft's own threads for
        # them made the start slower, not faster (400 patches of 64 x 64 px on 2 cores: 1.85 s
        # with two, 1.55 s with one; 3,600 patches: 18.5 -> 16.3 s).
        out: NDArray[np.complex64] = fft.rfft2(x.astype(np.float32), self.shape, axes=(-2, -1))
        return out

    def spectra(self, x: FloatArray, *, first: bool, dense: bool = False) -> _Spectra:
        """Spectra of channel stacks ``x`` (batch, C, h, w), NaN for missing pixels, as the
        ``first`` (``a``) or second image of their pairs; ``dense`` (every pixel of every
        image present, on both sides of the pairs) keeps summed-area tables instead of
        transforming masks and squares.

        Each channel is standardised on its own (its mean off, divided by its RMS) so that sums
        of squares do not cancel catastrophically; the NCC ignores both. First images are
        transformed upside down and back to front: their products with the second images'
        spectra are then convolutions that hold every shift in order, the most negative first
        (a correlation would wrap the negative shifts round to the end).
        """
        mask: NDArray[np.bool_] = np.all(np.isfinite(x), axis=1)
        x0 = np.where(mask[:, None], x - _masked_mean(x, mask[:, None]), 0.0)
        x0 = x0 / _rms(x0)
        if dense:
            if not mask.all():
                raise ValueError("dense spectra need images without missing pixels")
            return _Spectra(
                self._fft(x0[..., ::-1, ::-1] if first else x0),
                sums=_summed_area(x0),
                sums2=_summed_area(x0 * x0),
            )
        if first:
            x0, mask = x0[..., ::-1, ::-1], mask[..., ::-1, ::-1]
        return _Spectra(self._fft(x0), self._fft(mask), self._fft(x0 * x0))

    def _overlaps(self) -> tuple[tuple[IntArray, IntArray], ...]:
        """Per shift along each axis, the overlap's bounds in ``a`` and in ``b``: rows of a, rows
        of b, columns of a, columns of b, each as (start, stop) arrays over the shifts."""
        out: list[tuple[IntArray, IntArray]] = []
        for na, nb in zip(self.a, self.b, strict=True):
            d = np.arange(na + nb - 1) - (na - 1)  # b[y + d] meets a[y]
            lo, hi = np.maximum(0, -d), np.minimum(na, nb - d)
            out += [(lo, hi), (lo + d, hi + d)]
        return tuple(out)

    def _corr(self, x: NDArray[np.complex64], y: NDArray[np.complex64]) -> NDArray[np.float32]:
        # index (ha - 1, wa - 1) is the zero shift, shifts run from -(ha-1) to hb-1
        (ha, wa), (hb, wb) = self.a, self.b
        full = fft.irfft2(x * y, self.shape, axes=(-2, -1))
        out: NDArray[np.float32] = full[..., : ha + hb - 1, : wa + wb - 1]
        return out

    def ncc(self, fa: _Spectra, fb: _Spectra, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        """NCC (averaged over channels with weights ``w``) and overlap count of every pair
        ``(fa[k], fb[k])`` for every shift."""
        dense = fa.dense and fb.dense
        if dense:
            rows_a, rows_b, cols_a, cols_b = self._overlaps()
            size = (rows_a[1] - rows_a[0])[:, None] * (cols_a[1] - cols_a[0])[None, :]
            n = np.broadcast_to(size.astype(np.float64), (len(fa.values), *size.shape))
        else:
            n = np.rint(self._corr(_need(fa.mask), _need(fb.mask)))
        total = np.zeros(n.shape)
        for ch in range(len(w)):
            if w[ch] == 0:
                continue
            a1, b1 = fa.values[:, ch], fb.values[:, ch]
            sa: NDArray[np.floating[Any]]  # float64 sums or float32 transforms
            sb: NDArray[np.floating[Any]]
            saa: NDArray[np.floating[Any]]
            sbb: NDArray[np.floating[Any]]
            if dense:
                sa = _box(_need(fa.sums)[:, ch], rows_a, cols_a)
                saa = _box(_need(fa.sums2)[:, ch], rows_a, cols_a)
                sb = _box(_need(fb.sums)[:, ch], rows_b, cols_b)
                sbb = _box(_need(fb.sums2)[:, ch], rows_b, cols_b)
            else:
                sa, sb = self._corr(a1, _need(fb.mask)), self._corr(_need(fa.mask), b1)
                saa = self._corr(_need(fa.squares)[:, ch], _need(fb.mask))
                sbb = self._corr(_need(fa.mask), _need(fb.squares)[:, ch])
            sab = self._corr(a1, b1)
            with np.errstate(invalid="ignore", divide="ignore"):
                num = sab - sa * sb / n
                va = saa - sa**2 / n
                vb = sbb - sb**2 / n
                den = np.sqrt(np.clip(va, 0, None) * np.clip(vb, 0, None))
                # an overlap whose variance is within float32's rounding of zero is flat: no score
                total += w[ch] * np.where((n > 0) & (den > 1e-5 * n), num / den, np.nan)
        return np.clip(total, -1.0, 1.0), n.astype(np.float64)


def _need(x: NDArray[Any] | None) -> NDArray[Any]:
    if x is None:  # spectra of the other kind: an error of this module, not of its input
        raise RuntimeError("dense and masked spectra mixed in one NCC")
    return x


def pair_maps(
    images: Sequence[FloatArray],
    pairs: NDArray[np.intp],
    which: Sequence[int],
    *,
    weights: Sequence[float] | None = None,
    batch: int | None = None,
) -> Iterator[tuple[int, FloatArray, FloatArray, tuple[int, int]]]:
    """:func:`masked_ncc` of the pairs ``which`` (rows of ``pairs``, indices into ``images``).

    ``images`` are (h, w) or (channels, h, w) arrays. Pairs of equal shapes share one FFT
    lattice, every image on it is transformed once (:data:`SPECTRA_PAIRS` pairs' at a time at
    most), and their NCC maps are computed up to ``batch`` pairs at a time (default
    :data:`MAP_BATCH` at most). A few pairs take fewer: :data:`SPECTRA_SHARE` and
    :data:`MAP_SHARE` of them, at least 16 and 4 (:func:`chunk_size`). The maps are the same
    however the pairs are cut. Yields ``(row, ncc, count, zero)`` per pair.
    """
    spectra = chunk_size(len(which), SPECTRA_SHARE, SPECTRA_PAIRS, 16)
    if batch is None:
        batch = chunk_size(len(which), MAP_SHARE, MAP_BATCH, 4)
    stacks = [np.asarray(x, dtype=np.float64) for x in images]
    stacks = [x[None] if x.ndim == 2 else x for x in stacks]
    if any(x.ndim != 3 or x.shape[0] != stacks[0].shape[0] for x in stacks):
        raise ValueError("pair_maps needs images or stacks with the same channel count")
    w = _channel_weights(weights, stacks[0].shape[0])
    groups: dict[tuple[tuple[int, ...], tuple[int, ...]], list[int]] = {}
    for i in which:
        groups.setdefault((stacks[pairs[i, 0]].shape, stacks[pairs[i, 1]].shape), []).append(i)
    for (shape_a, shape_b), every in groups.items():
        lattice = _Lattice.of(shape_a, shape_b)
        # spectra for so many pairs at a time: for all pairs of a large mosaic at once they
        # took 60 bytes per input pixel (pairs come in patch order, so a chunk's images are
        # mostly its own and few are transformed twice)
        for first in range(0, len(every), spectra):
            members = every[first : first + spectra]
            yield from _group_maps(lattice, stacks, pairs, members, w, batch)


def _group_maps(
    lattice: _Lattice,
    stacks: Sequence[FloatArray],
    pairs: NDArray[np.intp],
    members: list[int],
    w: FloatArray,
    batch: int,
) -> Iterator[tuple[int, FloatArray, FloatArray, tuple[int, int]]]:
    """:func:`pair_maps` of ``members``, pairs of images of one shape each side."""
    rows = pairs[members]
    # every image once per side it takes in this group
    side_a, at_a = np.unique(rows[:, 0], return_inverse=True)
    side_b, at_b = np.unique(rows[:, 1], return_inverse=True)
    images_a = np.stack([stacks[c] for c in side_a.tolist()])
    images_b = np.stack([stacks[c] for c in side_b.tolist()])
    dense = bool(np.isfinite(images_a).all() and np.isfinite(images_b).all())
    spectra_a = lattice.spectra(images_a, first=True, dense=dense)
    spectra_b = lattice.spectra(images_b, first=False, dense=dense)
    for lo in range(0, len(members), batch):
        chunk = slice(lo, lo + batch)
        ncc, count = lattice.ncc(
            spectra_a.take(at_a.ravel()[chunk]), spectra_b.take(at_b.ravel()[chunk]), w
        )
        for j, i in enumerate(members[chunk]):
            yield i, ncc[j], count[j], lattice.zero


def _masked_mean(x: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    count = np.maximum(mask.sum(axis=(-2, -1), keepdims=True), 1)
    out: FloatArray = np.where(mask, x, 0.0).sum(axis=(-2, -1), keepdims=True) / count
    return out


def _rms(x: FloatArray) -> FloatArray:
    out: FloatArray = np.maximum(np.sqrt(np.mean(x**2, axis=(-2, -1), keepdims=True)), 1e-300)
    return out


def best_shift(
    a: FloatArray,
    b: FloatArray,
    *,
    weights: Sequence[float] | None = None,
    expected: tuple[float, float] = (0.0, 0.0),
    radius: tuple[float, float] | None = None,
    min_overlap: int = 16,
    prior: float = 0.0,
    ambiguity: float = 0.0,
) -> CorrelationPeak | None:
    """The NCC peak of ``b`` against ``a`` (images or channel stacks as for :func:`masked_ncc`)
    within ``radius`` of the ``expected`` shift: :func:`merge.start.peaks.find_peak` on their
    map."""
    ncc, count, zero = masked_ncc(a, b, weights=weights)
    return find_peak(
        ncc,
        count,
        zero,
        expected=expected,
        radius=radius,
        min_overlap=min_overlap,
        prior=prior,
        ambiguity=ambiguity,
    )
