"""Per-patch quality of a placement: residuals and how well each patch is placed.

Evaluated on the full-resolution heights for every method alike, so their reports compare
like with like: correspondences, residual RMS, the XY and Z standard deviations of each
patch's translation over the whole mosaic, and with every other patch held (whether its own
overlaps constrain XY at all: a flat or one-dimensional overlap does not).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core.information import signal_information
from merge.core.noise import patch_noise
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.bank import SurfaceBank
from merge.refine.normal_system import NormalSystem, build_normal_system
from merge.refine.state import MosaicState
from merge.report.uncertainty import gauge_modes, tied_groups, translation_sigmas

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: An XY direction with less than this fraction of a patch's larger own XY information is one
#: its overlaps do not see.
LOCAL_FLOOR = 1e-6


@dataclass(frozen=True)
class PatchFit:
    """Per-patch quality of a fit (metres, counts).

    ``xy_sigma`` (its larger axis) and ``z_sigma``: standard deviations of the translation, marginal
    over the whole mosaic with the gauge fixed (:mod:`merge.report.uncertainty`): how well the patch
    is placed. ``xy_sigma_local``: the same with every other patch held: whether its own overlaps
    constrain XY at all.
    """

    correspondences: int
    residual_rms: float
    xy_sigma: float
    z_sigma: float
    xy_sigma_local: float


def assess(
    patches: Sequence[Patch],
    pairs: IntArray,
    transforms: Sequence[PatchTransform],
    *,
    bank: SurfaceBank | None = None,
    system: NormalSystem | None = None,
    plane_sigma: FloatArray | None = None,
) -> list[PatchFit]:
    """Per-patch quality of given transforms on the full-resolution heights (no update).

    Used for every method, so their reports compare like with like. ``bank``: the patches' raw
    heights as surfaces, if already built (:attr:`merge.refine.icp.RefineResult.bank`).
    ``system``: the raw heights' system over ``pairs`` with its signal share, if already built
    where the transforms differ from these by a settled step (:attr:`RefineResult.system
    <merge.refine.icp.RefineResult>`: no height moved by a tenth of the noise); else it is built
    at ``transforms``. ``plane_sigma`` (2,): the drift planes' prior the refinement solved
    with (:attr:`RefineResult.plane_sigma <merge.refine.icp.RefineResult>`), counted into the
    uncertainties as its steps counted it (:func:`merge.report.uncertainty.translation_sigmas`);
    default none, the data alone.
    """
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    if bank is None:
        bank = SurfaceBank(patches, scale, 0.0, 1)
    state = MosaicState.from_transforms(transforms, bank, scale)
    noise = patch_noise((p.noise for p in patches), scale)
    if system is None or system.signal_vals is None:
        margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
        cand = bank.candidates(
            np.asarray(pairs, dtype=np.intp).reshape(-1, 2), state.R, state.s, margin
        )
        system = build_normal_system(bank, cand, state, noise, signal=True)
    checkpoint(1, "the uncertainty of every patch")
    n = len(patches)
    xy, z = np.full(n, np.inf), np.full(n, np.inf)
    if system.signal_vals is not None and len(system.rows):
        weight = bank.point_count.astype(np.float64)
        groups = tied_groups(system.rows, system.cols, n)
        checkpoint()  # each of these takes tenths of a second on 10,000 patches
        gauge = gauge_modes(state.s, bank.radius, weight, groups)
        checkpoint()
        xy, z = translation_sigmas(
            (system.rows, system.cols, system.signal_vals),
            gauge,
            rms=system.rms,
            z_design=system.line_design,
            positions=state.s[:, :2],
            plane_sigma=plane_sigma,
        )
    pitch = np.column_stack([bank.dx, bank.dy])
    local = _local_fits(system, n, noise, pitch, bank.slope_noise)
    # held by its neighbours, a patch is never placed better than its own overlaps allow (the
    # two take the noise's share out differently: per run there, per patch here)
    xy = np.maximum(xy, [local_xy for _, _, local_xy in local])
    return [
        PatchFit(k, rms * scale, float(xy[c] * scale), float(z[c] * scale), local_xy * scale)
        if k
        else PatchFit(0, float("nan"), float("inf"), float("inf"), float("inf"))
        for c, (k, rms, local_xy) in enumerate(local)
    ]


def _local_fits(
    stats: NormalSystem, n: int, noise: float, pitch: FloatArray, slope_noise: float
) -> list[tuple[int, float, float]]:
    """Per patch: residuals, their RMS and the XY standard deviation with every other patch
    held (pixel units). ``slope_noise``: variance of a looked-up slope of unit white noise per
    unit pitch (:func:`merge.core.heightfield.slope_noise`)."""
    out: list[tuple[int, float, float]] = []
    for c in range(n):
        checkpoint()  # 10,000 patches: half a second
        k = stats.count[c]
        if k == 0:
            out.append((0, float("nan"), float("inf")))
            continue
        rms = float(np.sqrt(stats.sq[c] / k))
        info = stats.diag[c] + 1e-9 * np.trace(stats.diag[c]) * np.eye(6)
        try:
            # information of its XY translation with its own other unknowns free, without the
            # share that slopes of noise contribute: noise is not texture (per residual
            # slope_noise σ² / pitch², 2/9 for bilinear look-ups between central differences;
            # a fraction of it where the sources' smoothed slopes stand in, slope_count)
            xy_info = info[:2, :2] - info[:2, 2:] @ np.linalg.solve(info[2:, 2:], info[2:, :2])
            pitch2 = np.array([pitch[c, 0] ** -2, pitch[c, 1] ** -2])
            slopes = k if stats.slope_count is None else stats.slope_count[c]
            xy_info = signal_information(xy_info, slopes * noise**2 * slope_noise * pitch2)
            vals = np.linalg.eigvalsh(xy_info)
            # at the level of the regularisation above, a direction is not seen at all
            seen = vals.min() > LOCAL_FLOOR * max(float(vals.max()), 1e-300)
            xy = float(rms / np.sqrt(vals.min())) if seen else float("inf")
        except np.linalg.LinAlgError:
            xy = float("inf")
        out.append((int(k), rms, xy))
    return out
