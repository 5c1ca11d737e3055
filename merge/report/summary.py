"""What the merge hands back: every patch's transform and quality, and the mosaic.

:func:`patch_reports` turns the assessment's fits (:func:`merge.report.quality.assess`) into
one :class:`PatchReport` per patch, with a warning for every patch whose overlaps hold its Z
but not its XY; :class:`MergeResult` gathers them with the mosaic and how the solver went.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from merge.config import MergeConfig
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.core.transforms import PatchTransform
from merge.refine.scanner import ScanDistortion
from merge.render import Mosaic
from merge.report.quality import PatchFit

FloatArray = NDArray[np.float64]

#: An XY standard deviation above this fraction of the pixel pitch means "XY not constrained".
XY_CONSTRAINED_FRACTION = 0.25
#: A patch whose overlaps leave a residual RMS above this many times what its noise explains
#: does not fit where the merge put it (:func:`misfit_ratio`). Over 2,825 patches of 240
#: variation draws (``benchmarks/merge_variations.py``, 0-39 and 1000-1199) the ratio stayed
#: at or under 1.6 (the real grating's, held or not; 1.17 at most for a patch the report held);
#: the tip-drawn grating at 40 nm pixels, where the cubic look-ups miss its flanks, leaves
#: about 2 (3 nm of residual under 1 nm of noise). A start 500 nm off on a folded sample
#: (draw 5581 at 15-25 % overlaps, 3 x 2 patches of 27 nm pixels, whose folds the noise
#: estimate counts in: 3.4-7.7 nm for 1.9) left four of its six patches at 5-8, every patch
#: held and turned up to 12 degrees.
MISFIT = 5.0


@dataclass(frozen=True)
class PatchReport:
    """What the merge did to one patch and how well it fits.

    Attributes
    ----------
    transform
        ``T_mosaic_patch`` (rigid motion plus in-patch drift plane, metres).
    rotation, translation
        the rigid transform closest to ``transform`` over the patch's points,
        for consumers that only understand ``q = R p + t``.
    overlaps
        whether any other patch can overlap it (otherwise it stays nominal).
    correspondences
        overlap points that entered the fit.
    residual_rms
        RMS normal distance of those points to the other patches, metres.
    xy_constrained
        whether its own overlaps pin down XY (a flat overlap constrains only Z).
    xy_sigma, z_sigma
        standard deviations of its translation (XY: the larger axis), metres,
        marginal over the whole mosaic with its common motion fixed: a block of patches tied to
        the rest by little texture is as uncertain as the block (:mod:`merge.report.uncertainty`).
    """

    id: str
    transform: PatchTransform
    rotation: FloatArray
    translation: FloatArray
    overlaps: bool
    correspondences: int
    residual_rms: float
    xy_constrained: bool
    xy_sigma: float
    z_sigma: float


@dataclass(frozen=True)
class MergeResult:
    """The mosaic, every patch's transform and quality, and how the solver went."""

    mosaic: Mosaic
    patches: list[PatchReport]
    method: str
    config: MergeConfig
    iterations: int
    converged: bool
    history: list[float]
    warnings: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    #: the scanner's bend taken out of every patch (``MergeConfig.self_calibrate``), or None
    distortion: ScanDistortion | None = None

    @property
    def transforms(self) -> list[PatchTransform]:
        """``T_mosaic_patch`` in patch order."""
        return [p.transform for p in self.patches]


def holds_xy(fit: PatchFit, patch: Patch) -> bool:
    """Whether ``patch``'s own overlaps pin its XY down, as ``fit`` measured them (its XY
    standard deviation with every other patch held within :data:`XY_CONSTRAINED_FRACTION` of its
    pixel pitch)."""
    return fit.correspondences > 0 and fit.xy_sigma_local < XY_CONSTRAINED_FRACTION * min(
        patch.pixel_size
    )


def misfit_ratio(fit: PatchFit, patch: Patch) -> float:
    """``patch``'s residual RMS over its overlaps (``fit``) over what its white noise explains
    (sqrt(2) times it: two noisy surfaces meet): about 1 where it lies where its neighbours
    say, less where the look-ups average noise away. NaN where it has no overlap point or no
    noise could be estimated (noise-free data: nothing to judge the misfit by)."""
    noise = patch.noise
    if fit.correspondences <= 0 or not math.isfinite(noise) or noise <= 0:
        return float("nan")
    return fit.residual_rms / (math.sqrt(2.0) * noise)


def patch_reports(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    fits: Sequence[PatchFit],
    linked: NDArray[np.bool_],
    *,
    registered: bool,
    unsettled: NDArray[np.bool_] | None = None,
    unconfirmed: dict[int, float] | None = None,
    untied: dict[int, tuple[str, ...]] | None = None,
) -> tuple[list[PatchReport], list[str]]:
    """One report per patch, and a warning for each whose overlaps do not fit where it lies
    (:func:`misfit_ratio` past :data:`MISFIT`), whose overlaps constrain Z but not XY, which
    the refinement stopped before it had settled, or whose texture does not confirm where the
    refinement alone put it.

    Parameters
    ----------
    patches : sequence of Patch
    transforms : sequence of PatchTransform
        ``T_mosaic_patch`` per patch, as the merge left them.
    fits : sequence of PatchFit
        The assessment of those transforms (:func:`merge.report.quality.assess`).
    linked : (n,) bool array
        Whether each patch can overlap any other.
    registered : bool, keyword-only
        Whether the method registered XY (the default and paper methods): only then is an
        XY its overlaps cannot hold worth a warning.
    unsettled : (n,) bool array, keyword-only
        Patches the refinement still moved when it ran out of iterations
        (:class:`merge.refine.RefineResult`): their XY is where it stopped, not a measurement,
        however sharp the fit looks there (a 1-D grating's patches, placed by the start a
        stripe's width along the stripes from the truth, crept along them for 30 steps and
        stopped 150 nm off, each claiming 1 nm). Default none.
    unconfirmed : dict, keyword-only
        Patches (index: the rise of their misfit when moved, in standard errors) that the
        refinement alone placed and whose texture does not confirm it
        (:func:`merge.report.confirmation.unconfirmed`): their XY is a dip of the noise as
        likely as a registration. Default none.
    untied : dict, keyword-only
        Patches (index: the names of the axes) that no chain of overlaps which measured them
        ties to the mosaic's largest block along those axes (:func:`merge.report.ties.untied`).
        Default none.
    """
    unconfirmed, untied = unconfirmed or {}, untied or {}
    reports, warnings = [], []
    for c, p in enumerate(patches):
        checkpoint()
        f = fits[c]
        stopped = unsettled is not None and bool(unsettled[c])
        doubted = c in unconfirmed
        misfit = misfit_ratio(f, p)
        astray = misfit > MISFIT
        xy_ok = holds_xy(f, p) and not stopped and not doubted and c not in untied and not astray
        xx, yy = p.pixel_coordinates()
        sample = np.column_stack([xx.ravel(), yy.ravel(), p.heights.ravel()])[::7]
        R_rigid, t_rigid = transforms[c].rigid_approximation(sample[np.isfinite(sample[:, 2])])
        reports.append(
            PatchReport(
                id=p.id,
                transform=transforms[c],
                rotation=R_rigid,
                translation=t_rigid,
                overlaps=bool(linked[c]),
                correspondences=f.correspondences,
                residual_rms=f.residual_rms,
                xy_constrained=bool(xy_ok),
                xy_sigma=f.xy_sigma,
                z_sigma=f.z_sigma,
            )
        )
        if linked[c] and astray and registered:
            warnings.append(
                f"patch {p.id!r}: its overlaps do not fit where the merge put it (residual RMS "
                f"{f.residual_rms * 1e9:.1f} nm, {misfit:.0f} x what its noise explains); its "
                "place is not a measurement (a start a feature's width off? the sample or the "
                "tip changed while it was scanned?)"
            )
        elif linked[c] and stopped and registered:
            warnings.append(
                f"patch {p.id!r}: the refinement ran out of iterations while it still moved "
                "this patch; its XY is where the fit stopped, not a measurement (its overlaps "
                "may hold XY along one direction only, as a grating's stripes do)"
            )
        elif linked[c] and doubted and registered:
            rise = unconfirmed[c]
            why = (
                f"moved off it by a few pixels, its misfit rises by only {rise:.1f} standard errors"
                if math.isfinite(rise)
                else "no move off it keeps enough of its points over its neighbours to tell"
            )
            warnings.append(
                f"patch {p.id!r}: the refinement alone placed it (the start could not measure "
                f"it) and its texture does not confirm the place: {why}; its XY is a guess, "
                "not a measurement (a texture weaker than the noise?)"
            )
        elif linked[c] and c in untied and registered:
            axes = ", ".join(untied[c])
            warnings.append(
                f"patch {p.id!r}: no chain of overlaps that measured it ties it to the largest "
                f"block of the mosaic along {axes} (overlaps too narrow or too flat along it); "
                "where its block lies against the rest is the stage's placement, not a "
                "measurement"
            )
        elif linked[c] and not xy_ok and registered:
            warnings.append(
                f"patch {p.id!r}: its overlaps constrain Z but not XY (too flat or a 1-D "
                "structure); its XY there is a guess, not a measurement"
            )
    return reports, warnings
