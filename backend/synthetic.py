"""Synthetic patch sets as merge inputs, and scoring a merge against their truth.

Ties the simulated world (``hardware.sim``) to the merge engine; the CLI, the benchmarks and
the tests share it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from hardware.sim.synth import SynthPatch, true_points
from merge import Patch, PatchSet, PatchTransform
from merge.core.kabsch import weighted_rigid_transform

FloatArray = NDArray[np.float64]


def patch_set_from_synth(synth: Sequence[SynthPatch]) -> PatchSet:
    """The merge's view of synthetic patches (without their truth)."""
    return PatchSet(
        Patch(
            id=s.id,
            heights=s.heights,
            origin=s.origin,
            pixel_size=s.pixel_size,
            order=s.order,
            row=s.row,
            col=s.col,
        )
        for s in synth
    )


def _placed(
    synth: Sequence[SynthPatch], transforms: Sequence[PatchTransform], stride: int = 1
) -> list[tuple[FloatArray, FloatArray]]:
    """Per patch: where the merge puts every measured point (every ``stride``-th along both
    axes), and where it truly is (m, 3)."""
    out = []
    for s, tr in zip(synth, transforms, strict=True):
        ny, nx = s.heights.shape
        xx, yy = np.meshgrid(
            s.origin[0] + np.arange(nx) * s.pixel_size[0],
            s.origin[1] + np.arange(ny) * s.pixel_size[1],
        )
        p = np.stack([xx, yy, s.heights], axis=-1)[::stride, ::stride].reshape(-1, 3)
        q = true_points(s)[::stride, ::stride].reshape(-1, 3)
        ok = np.isfinite(p).all(axis=1) & np.isfinite(q).all(axis=1)
        out.append((tr.apply(p[ok]), q[ok]))
    return out


def _gauge(
    placed: list[tuple[FloatArray, FloatArray]],
) -> tuple[FloatArray, FloatArray, tuple[FloatArray, FloatArray]]:
    """All placed and true points, and the global rigid transform that fits them best."""
    P, Q = np.concatenate([p for p, _ in placed]), np.concatenate([q for _, q in placed])
    return P, Q, weighted_rigid_transform(P, Q)


def registration_error(
    synth: Sequence[SynthPatch], transforms: Sequence[PatchTransform], *, stride: int = 1
) -> tuple[float, float, tuple[FloatArray, FloatArray]]:
    """RMS XY and Z error (metres) of where the merge puts every measured point, after the one
    global rigid transform that fits best (the gauge), and that transform ``(G, g)``.
    ``stride``: every so many points along both axes of a patch (large mosaics)."""
    if stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride}")
    P, Q, (G, g) = _gauge(_placed(synth, transforms, stride))
    e = P @ G.T + g - Q
    exy = float(np.sqrt(np.mean(np.sum(e[:, :2] ** 2, axis=1))))
    return exy, float(np.sqrt(np.mean(e[:, 2] ** 2))), (G, g)


def patch_errors(synth: Sequence[SynthPatch], transforms: Sequence[PatchTransform]) -> FloatArray:
    """Mean error (n, 3), metres, of where the merge puts each patch's points, after the global
    rigid transform of :func:`registration_error`: what each patch's sigmas should cover."""
    placed = _placed(synth, transforms)
    _, _, (G, g) = _gauge(placed)
    out: FloatArray = np.array([(p @ G.T + g - q).mean(axis=0) for p, q in placed])
    return out


def sigma_calibration(
    errors: FloatArray, xy_sigma: FloatArray, z_sigma: FloatArray
) -> dict[str, float]:
    """How honest reported sigmas are: RMS of error / sigma over the patches with finite ones,
    XY per axis (the larger axis's sigma): 1 is honest, below is cautious, above over-confident."""
    xy_ok, z_ok = np.isfinite(xy_sigma) & (xy_sigma > 0), np.isfinite(z_sigma) & (z_sigma > 0)
    xy = np.sum(errors[xy_ok, :2] ** 2, axis=1) / (2.0 * xy_sigma[xy_ok] ** 2)
    z = errors[z_ok, 2] ** 2 / z_sigma[z_ok] ** 2
    return {
        "xy": float(np.sqrt(xy.mean())) if xy.size else float("nan"),
        "z": float(np.sqrt(z.mean())) if z.size else float("nan"),
    }
