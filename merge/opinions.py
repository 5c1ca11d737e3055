"""Other opinions on the start's placement: the refinement again from other placements, and the
fit that leaves the overlaps the least misfit (step 4 of :mod:`merge.pipeline`).

The refinement settles in the minimum next to where the start put the patches. Where the start
may have put a block of them wrong, another placement leads to another minimum of the same
data, and the lower misfit is the likelier placement. Three such placements are tried:

- the stage's (every patch where the stage put it), where the report cannot vouch for the XY
  of :data:`DOUBT_SHARE` of the linked patches: the start's pairs then placed a block a few
  cells off while claiming a tenth of one, and the stage's placement does not depend on them;
- the first fit with only the patches the report cannot vouch for put back where the stage put
  them, where those are fewer than :data:`DOUBT_SHARE`: one patch the start put a feature's
  width off is a minimum of its own, which the rest, well placed, need not leave;
- the start's alternatives (:mod:`merge.start.hypotheses`), where its pairs' votes split
  between placements: a block the report holds, because every pair the network kept holds it,
  can still be the wrong one of two the pairs allow.

A merge whose patches the report holds and whose start's pairs agree costs nothing more.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from merge.config import MergeConfig
from merge.core.errors import listed
from merge.core.patchset import Patch
from merge.core.progress import stage
from merge.core.transforms import PatchTransform
from merge.finish import Judged, judge
from merge.records import Layout, Placement, Solution, Stopwatch
from merge.refine.bank import SurfaceBank
from merge.report import PatchReport
from merge.report.common_points import CommonMisfit, common_misfit

#: Called after every iteration with (iteration, residual RMS in metres).
Progress = Callable[[int, float], None]
#: The refinement from a placement, its iterations told to the progress given.
Refit = Callable[[Placement, Progress], Solution]

#: Iterations a merge typically takes (9-10 from 100 to 2,500 patches): a refinement's share
#: of the progress bar.
TYPICAL_ITERATIONS = 10
#: Share of the linked patches whose XY the report cannot vouch for (not ``xy_constrained``)
#: from which the start's placement is in doubt as a whole (:func:`second_opinion`).
DOUBT_SHARE = 0.2
#: How many points' worth of misfit the merge from another placement must explain better than
#: the start's, on the points both overlap (:attr:`CommonMisfit.evidence
#: <merge.report.common_points.CommonMisfit>`), to replace it. Points are not independent: a
#: tip-drawn flank or a fold misfits along its length, and a patch's residuals move together over
#: tens of pixels. Over the 1,514 variation draws of the fresh block 5000-5999 that had fits
#: from other placements, the summed error of the worst patch of the fits kept is flat from 250
#: to 350 points' worth and grows either side (100: 5 % more, none: 24 %). Below the bar stay
#: wrong fits of small mosaics (TGX1 5385 and 5610 at 15-25 %: 259 and 275) and some true
#: places too (TGX1 5525: 183, MoS2 5152: 298). A share of the RMS instead (1 % less) refused
#: a MoS2 fit from the true places that explained 5,570 points' worth over its 280,000 (5202).
EVIDENCE = 300.0
#: ... and this many times the square root of the points both overlap: the spread of the
#: evidence between two fits equally good grows with the points, and over MoS2's hundreds of
#: thousands 300 points' worth is a thousandth of the misfit. A fit with a patch 440 nm off
#: explained 337 more than the start's right one over 300,000 points (draw 1077 of a block
#: checked on: 1.09 -> 2.85 x the floor). Over the fresh block and draws 1000-1199 (1,753 draws
#: with candidates; evidence against the start's), the fits kept that were worse than the
#: start's by 5 nm or more: 18 with 300 points' worth alone, 13 with 3 roots, 11 with 4.
EVIDENCE_ROOTS = 3.0


def convincing(common: CommonMisfit) -> bool:
    """Whether a fit explains the points both overlap better than another by enough: by
    :data:`EVIDENCE` points' worth of misfit and :data:`EVIDENCE_ROOTS` square roots of their
    count."""
    return common.evidence >= max(EVIDENCE, EVIDENCE_ROOTS * float(np.sqrt(common.points)))


def keeps_overlaps(before: Sequence[PatchReport], after: Sequence[PatchReport]) -> bool:
    """Whether every patch of a fit (``after``) that had overlap points in the fit it would
    replace (``before``) still has some. The residual RMS is taken over the points that
    overlap: a fit that slides a patch off its neighbours sheds its misfit with them (a MoS2
    draw, 5377: a corner patch moved 300 nm off its place overlapped nothing, and the mosaic
    came out 33 x the floor at 2 % less residual). Fewer points alone say nothing: a block put
    back where it belongs often overlaps less than where the wrong peaks had it (5975, 5960:
    the pairs' correlation favours the larger overlap)."""
    return not any(
        b.correspondences > 0 and a.correspondences == 0 for b, a in zip(before, after, strict=True)
    )


def second_opinion(
    patches: Sequence[Patch],
    layout: Layout,
    placed: Placement,
    cfg: MergeConfig,
    watch: Stopwatch,
    first: tuple[Solution, Judged],
    *,
    refit: Refit,
    progress: Progress | None,
) -> tuple[Solution, Judged]:
    """The refinement again from the stage's placement, where the report cannot vouch for the
    XY of :data:`DOUBT_SHARE` of the linked patches or more (of fewer: from the first fit with
    those patches at the stage's places, :func:`_loose_from_stage`), and from each of the start's
    alternatives (``placed.alternatives``). Each is compared with the ``first`` (the start's)
    on the points both overlap (:func:`merge.report.common_points.common_misfit`): it must
    explain the misfit better there by enough (:func:`convincing`). Those are taken in the order
    of that evidence, each weighed against the fit kept so far the same way (their evidence
    against the start's is over different points); a fit is kept only if it keeps every patch's
    overlaps (:func:`keeps_overlaps`). None kept: the ``first``.

    The residual RMS over each fit's own overlap points judged them before: a fit that slid a
    patch partly off its neighbours shed its misfit with them and won (MoS2 draw 5372: a corner
    patch kept 622 of its 9,181 points, 0.3 % less residual than the fit from the true places,
    3.17 x the floor where they give 0.95; folded 1066 at 15-25 %: the start's right placement,
    1.05 x, lost to a fit 170 nm off, 45 x). On the common points the true places win there
    (5372: 0.83 of the start's RMS, the sliding fit 0.93; 1066: the sliding fit no better).

    The stage's placement: the start's pairs can place a whole block of patches a few cells
    off while claiming a tenth of one (a 22 x 45 px TGX1 patch's overlaps filled by ramp
    flanks: a correlation peak shifted along an edge, a tail of a ramp that is its own copy
    scaled), and the refinement then settles in the local minimum next to it, where the report
    finds the patches unconfirmed (no chain of measured overlaps ties them). The stage's
    placement does not depend on those pairs; both minima are of the same data, so the lower
    misfit is the likelier placement (of five such TGX1 draws, the fit from the true places
    left 4-22 % less residual RMS than the start's every time). Over 460 variation draws
    (``benchmarks/merge_variations.py``), at 25-50 % overlaps (draws 0-39, 500-559,
    1000-1199) TGX1's 510, 535 and 540 went from 16.6, 20.6 and 13.6 x the floor to 1.6, 1.1
    and 1.5, no draw worse (1030 and 1105 stay gross: the stage's placement leads to a
    minimum as wrong, with more misfit); at 15-25 % (draws 0-39, 500-539, 1000-1199) MoS2's
    silent patches 9 -> 2 (draw 1012 2.8 -> 1.0 x, 537 1.7 -> 1.25), TGX1's 1060 and 1195
    13 -> 1.5 and 2.5 x, and one draw worse, TGX1's 520, gross either way (17.8 -> 37 x, 8
    patches unconfirmed instead of 4).
    Restarting only the unconfirmed patches from the stage mended two of the five and left
    four silent patches on the real grating, so every patch restarts there; under the share
    only those restart (the rest lie where the first fit put them, not where the start did).

    :func:`merge.pipeline.merge_once` asks for none on a sample it said periodic: a patch a
    whole repeat off fits about as well (on the real grating the choice mended 2 gross draws
    and made 4 worse). ``refit`` refines from a placement; ``progress`` is told every fit's
    iterations numbered on from the ``first``'s.
    """
    solution, judged = first
    linked = np.flatnonzero(layout.linked)
    loose = [c for c in linked.tolist() if not judged[0][c].xy_constrained]
    doubted = len(loose)
    tried: list[tuple[str, Placement]] = []
    if len(linked) and doubted >= DOUBT_SHARE * len(linked):
        stage_placed = Placement(
            [PatchTransform(centre=np.array(p.center)) for p in patches],
            ~layout.linked,
            placed.pair_information,
            placed.repeat,
        )
        tried.append(("stage", stage_placed))
    elif doubted:
        tried.append(("loose", _loose_from_stage(patches, placed, solution, loose)))
    count = 0 if placed.alternatives is None else len(placed.alternatives)
    tried += [("votes", placed.alternative(i)) for i in range(count)]
    if not tried or not solution.history:
        return first
    done = solution.iterations
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    fits: list[tuple[CommonMisfit, int, str, Solution]] = []
    detail = "refining again from another placement"
    with watch.step("second_opinion"), stage("refine", TYPICAL_ITERATIONS * len(tried), detail):
        for order, (name, other_placed) in enumerate(tried):

            def counted_on(iteration: int, residual: float, offset: int = done) -> None:
                """This fit's iterations numbered on from the fits before it."""
                if progress is not None:
                    progress(offset + iteration, residual)

            other = refit(other_placed, counted_on)
            done += other.iterations
            if not other.history:
                continue
            bank = other.bank or SurfaceBank(patches, scale, 0.0, 1)
            common = common_misfit(
                bank, layout.pairs, solution.transforms, other.transforms, scale=scale
            )
            if convincing(common):
                fits.append((common, order, name, other))
    # the most evidence first, each against the fit kept so far (two candidates' evidence
    # against the start's is over different points), of those that keep the overlaps: a fit
    # that slides a patch off its neighbours leaves fewer and better points, not a better
    # placement
    chosen = None
    for common, _, name, other in sorted(fits, key=lambda f: (-f[0].evidence, f[1])):
        if chosen is not None:
            held = chosen[2]
            bank = other.bank or SurfaceBank(patches, scale, 0.0, 1)
            versus = common_misfit(
                bank, layout.pairs, held.transforms, other.transforms, scale=scale
            )
            if not convincing(versus):
                continue
        reports, unheld = judge(patches, layout, other, cfg, watch)
        if keeps_overlaps(judged[0], reports):
            chosen = (common, name, other, reports, unheld)
    if chosen is None:
        return first
    common, kind, best, reports, unheld = chosen
    before = np.sqrt(common.before / common.points) * 1e9
    after = np.sqrt(common.after / common.points) * 1e9
    on = f"on the {common.points} points both overlap"
    if kind == "loose":
        names = [patches[c].id for c in loose]
        said = (
            f"the merge could not confirm the place of {doubted} of {len(linked)} patches "
            f"({listed(names, 6)}): put back where the stage put them, the rest where the "
            f"merge had them, it fits the overlaps better (residual RMS {on} {before:.2f} -> "
            f"{after:.2f} nm) and is the one kept"
        )
    elif kind == "stage":
        said = (
            f"the start's placement was not borne out ({doubted} of {len(linked)} patches' XY "
            "unconfirmed after the merge from it): the merge from the stage's placement fits "
            f"the overlaps better (residual RMS {on} {before:.2f} -> {after:.2f} nm) and is "
            "the one kept"
        )
    else:
        said = (
            "the start's pairs allowed another placement (their votes split, or a pair's peak "
            "repeats itself): the merge from it fits the overlaps better (residual RMS "
            f"{on} {before:.2f} -> {after:.2f} nm) and is the one kept"
        )
    return best, (reports, [said, *unheld])


def _loose_from_stage(
    patches: Sequence[Patch],
    placed: Placement,
    solution: Solution,
    loose: Sequence[int],
) -> Placement:
    """The first fit (``solution``) with the linked patches its report could not confirm
    (``loose``, indices; fewer than :data:`DOUBT_SHARE`) put back where the stage put them, as
    patches the start did not measure: a start that put one patch a feature's width off (a
    corner patch of a tip-drawn chessboard, 1 µm patches at 20 nm pixels, 420 nm off where the
    stage had it 131 nm off; ``merge_bench --gratings`` draw 3) leaves the refinement a minimum
    its overlaps do not fit, and from the stage it settles 3 nm from the truth."""
    transforms = list(solution.transforms)
    measured = placed.measured_both.copy()
    for c in loose:
        transforms[c] = PatchTransform(centre=np.array(patches[c].center))
        measured[c] = False
    return Placement(transforms, measured, placed.pair_information, placed.repeat)
