"""A small mosaic with known truth for the heights' last solve's tests: 3 x 3 patches of a
smooth surface, each scanned with a Z offset, scan-line offsets and white noise."""

from __future__ import annotations

import numpy as np

from merge.core.overlap import overlapping_pairs
from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform

PIXEL = 10e-9
SIDE = 48
STEP = 36  # pixels between neighbours: overlaps of 12 px
TAU = 0.5e-9
NOISE = 0.2e-9


def surface(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth rough surface (metres): a few waves, some tens of nm long."""
    out = np.zeros_like(x)
    rng = np.random.default_rng(7)
    for _ in range(12):
        k = rng.uniform(2 * np.pi / 300e-9, 2 * np.pi / 60e-9) * np.array(
            [np.cos(a := rng.uniform(0, np.pi)), np.sin(a)]
        )
        out += 2e-9 * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 2 * np.pi))
    return out


def mosaic(
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
        h = surface(origin[0] + xx * PIXEL, origin[1] + yy * PIXEL)
        c = rng.normal(0.0, tau, SIDE)
        h = h + offsets[k] + c[:, None] + rng.normal(0.0, NOISE, h.shape)
        patches.append(Patch(f"p{k}", h, origin, (PIXEL, PIXEL)))
        centre = np.array(origin) + 0.5 * (SIDE - 1) * PIXEL
        truth.append(PatchTransform(t=np.array([0.0, 0.0, -offsets[k]]), centre=centre))
        lines.append(c)
    return patches, truth, offsets, lines


def pairs_of(patches: list[Patch]) -> np.ndarray:
    boxes = np.array(
        [[*p.origin, p.origin[0] + SIDE * PIXEL, p.origin[1] + SIDE * PIXEL] for p in patches]
    )
    return overlapping_pairs(boxes)


def height_errors(
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


def disturbed(truth: list[PatchTransform], seed: int = 1) -> list[PatchTransform]:
    """The true transforms with every patch's Z (1 nm) and drift plane (1 nm at its edge) off."""
    rng = np.random.default_rng(seed)
    out = []
    for T in truth:
        t = T.t.copy()
        t[2] += rng.normal(0.0, 1e-9)
        slope = rng.normal(0.0, 1e-9 / (0.5 * SIDE * PIXEL), 2)
        out.append(PatchTransform(T.R, t, slope, T.centre))
    return out
