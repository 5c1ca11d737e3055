"""Minimal PNG writing and text for previews: numpy and the standard library only."""

from __future__ import annotations

import struct
import zlib

import numpy as np
from numpy.typing import NDArray

UInt8Array = NDArray[np.uint8]


def encode_png(rgb: UInt8Array) -> bytes:
    """PNG bytes of an ``(h, w, 3)`` uint8 image."""
    img = np.ascontiguousarray(rgb, dtype=np.uint8)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"need an (h, w, 3) image, got {img.shape}")
    h, w, _ = img.shape
    raw = np.zeros((h, 1 + 3 * w), dtype=np.uint8)  # filter byte 0 (None) per row
    raw[:, 1:] = img.reshape(h, 3 * w)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + tag
            + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


# 5 x 7 glyphs, '#' = ink; only what the previews write
_GLYPHS = {
    "0": [".###.", "#...#", "#..##", "#.#.#", "##..#", "#...#", ".###."],
    "1": ["..#..", ".##..", "..#..", "..#..", "..#..", "..#..", ".###."],
    "2": [".###.", "#...#", "....#", "...#.", "..#..", ".#...", "#####"],
    "3": ["####.", "....#", "....#", ".###.", "....#", "....#", "####."],
    "4": ["...#.", "..##.", ".#.#.", "#..#.", "#####", "...#.", "...#."],
    "5": ["#####", "#....", "####.", "....#", "....#", "#...#", ".###."],
    "6": [".###.", "#....", "#....", "####.", "#...#", "#...#", ".###."],
    "7": ["#####", "....#", "...#.", "..#..", ".#...", ".#...", ".#..."],
    "8": [".###.", "#...#", "#...#", ".###.", "#...#", "#...#", ".###."],
    "9": [".###.", "#...#", "#...#", ".####", "....#", "....#", ".###."],
    "-": [".....", ".....", ".....", "#####", ".....", ".....", "....."],
    ".": [".....", ".....", ".....", ".....", ".....", ".##..", ".##.."],
    " ": [".....", ".....", ".....", ".....", ".....", ".....", "....."],
    "n": [".....", ".....", "####.", "#...#", "#...#", "#...#", "#...#"],
    "m": [".....", ".....", "##.#.", "#.#.#", "#.#.#", "#.#.#", "#.#.#"],
    "µ": [".....", ".....", "#..#.", "#..#.", "#..#.", "###.#", "#...."],
    "A": [".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"],
    "D": ["####.", "#...#", "#...#", "#...#", "#...#", "#...#", "####."],
    "E": ["#####", "#....", "#....", "####.", "#....", "#....", "#####"],
    "F": ["#####", "#....", "#....", "####.", "#....", "#....", "#...."],
    "G": [".###.", "#...#", "#....", "#.###", "#...#", "#...#", ".###."],
    "I": [".###.", "..#..", "..#..", "..#..", "..#..", "..#..", ".###."],
    "L": ["#....", "#....", "#....", "#....", "#....", "#....", "#####"],
    "M": ["#...#", "##.##", "#.#.#", "#.#.#", "#...#", "#...#", "#...#"],
    "N": ["#...#", "##..#", "#.#.#", "#..##", "#...#", "#...#", "#...#"],
    "O": [".###.", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."],
    "R": ["####.", "#...#", "#...#", "####.", "#.#..", "#..#.", "#...#"],
    "T": ["#####", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."],
}


def text_mask(text: str, scale: int = 2) -> NDArray[np.bool_]:
    """A boolean ink mask of ``text`` in the built-in 5 x 7 font (unknown characters blank)."""
    cols = []
    for ch in text:
        rows = _GLYPHS.get(ch, _GLYPHS[" "])
        glyph = np.array([[c == "#" for c in r] for r in rows], dtype=bool)
        cols.append(np.pad(glyph, ((0, 0), (0, 1))))
    mask = np.concatenate(cols, axis=1) if cols else np.zeros((7, 0), dtype=bool)
    out: NDArray[np.bool_] = np.kron(mask, np.ones((scale, scale), dtype=bool))
    return out


def draw_text(
    img: UInt8Array, text: str, row: int, col: int, *, color: tuple[int, int, int], scale: int = 2
) -> None:
    """Write ``text`` into ``img`` (in place) with its top-left corner at ``(row, col)``."""
    mask = text_mask(text, scale)
    h, w = mask.shape
    r1, c1 = min(row + h, img.shape[0]), min(col + w, img.shape[1])
    if r1 <= row or c1 <= col:
        return
    region = img[row:r1, col:c1]
    region[mask[: r1 - row, : c1 - col]] = color
