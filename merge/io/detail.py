"""Levels of detail of a large mosaic: the means of k x k blocks of heights.

A mosaic of ten thousand patches holds about a hundred million heights; a browser's scene or a
preview wants a million at most. Every ``k``-th height alone would alias the texture (a
grating's period folded onto the sampling); the mean of each block does not, and a block with
any finite height keeps one. The heights are read a band of ``k`` rows at a time from any
source that slices like an array (an array, a memory-mapped ``.npy``, an HDF5 dataset), so a
level of detail never holds the whole mosaic.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Rows(Protocol):
    """What a source of heights must do: a 2-D shape, and bands of rows by slicing."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    def __getitem__(self, key: slice) -> NDArray[np.floating]: ...


#: Heights read at a time (a band of whole blocks of rows), at most: a few MB.
BAND_VALUES = 1 << 20


def detail_step(shape: tuple[int, ...], budget: int) -> int:
    """The smallest block side ``k`` that leaves at most ``budget`` (>= 1) blocks of a map of
    ``shape`` (ny, nx)."""
    if budget < 1:
        raise ValueError(f"a level of detail needs a budget of at least 1 value, got {budget}")
    ny, nx = shape[:2]
    k = max(1, int(np.ceil(np.sqrt(ny * nx / budget))))
    while -(-ny // k) * -(-nx // k) > budget:
        k += 1
    return k


def detail_frame(
    origin: tuple[float, float], pixel_size: tuple[float, float], k: int
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Where the values of :func:`block_means` stand: the first block's centre, and one block
    a pixel (``origin`` the centre of pixel (0, 0), any unit)."""
    centre = 0.5 * (k - 1)
    return (
        (origin[0] + centre * pixel_size[0], origin[1] + centre * pixel_size[1]),
        (k * pixel_size[0], k * pixel_size[1]),
    )


def block_means(heights: Rows, k: int) -> FloatArray:
    """Mean of every ``k`` x ``k`` block of ``heights`` (ny, nx), NaN ignored (NaN where a block
    holds none); blocks at the far edges are what is left. Returns (ceil(ny / k), ceil(nx / k)).
    """
    if k < 1:
        raise ValueError(f"blocks must be at least 1 x 1, got k={k}")
    if len(heights.shape) != 2:
        raise ValueError(f"need a 2-D map of heights, got shape {heights.shape}")
    ny, nx = heights.shape
    my, mx = -(-ny // k), -(-nx // k)
    out = np.empty((my, mx))
    rows = max(1, BAND_VALUES // max(k * nx, 1)) * k  # whole blocks of rows per band
    for lo in range(0, ny, rows):
        band = np.asarray(heights[lo : lo + rows], dtype=np.float64)
        h = band.shape[0]
        padded = np.full((-(-h // k) * k, mx * k), np.nan)
        padded[:h, :nx] = band
        blocks = padded.reshape(-1, k, mx, k)
        finite = np.isfinite(blocks)
        count = finite.sum(axis=(1, 3))
        total = np.where(finite, blocks, 0.0).sum(axis=(1, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            out[lo // k : lo // k + len(count)] = np.where(count > 0, total / count, np.nan)
    return out
