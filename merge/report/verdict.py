"""The merge's verdict for a person: is the mosaic's every place measured, or not to be
trusted? One line, and the patches it is about."""

from __future__ import annotations

from dataclasses import dataclass

from merge.core.errors import listed
from merge.report.summary import MergeResult

#: Methods that measure XY from the overlaps (the others level Z, or keep the stage's XY).
REGISTERING = ("default", "paper")


@dataclass(frozen=True)
class Verdict:
    """``trusted``: whether the mosaic's places are measured; ``line``: what to tell a person
    (the last line of a merge); the patches that overlap no other, and those linked patches
    whose XY the merge could not confirm (stopped moving, texture too weak, untied)."""

    trusted: bool
    line: str
    isolated: tuple[str, ...]
    unconfirmed: tuple[str, ...]


def verdict(result: MergeResult) -> Verdict:
    """Not trusted when no two patches overlap, when any patch overlaps no other (its place
    is the stage's or the file's, never measured), or, for a registering method, when most
    linked patches have an XY the merge could not confirm."""
    patches = result.patches
    isolated = tuple(p.id for p in patches if not p.overlaps)
    linked = [p for p in patches if p.overlaps]
    registering = result.method in REGISTERING
    loose = tuple(p.id for p in linked if registering and not p.xy_constrained)
    n = len(patches)
    if not linked or not any(p.correspondences for p in linked):
        line = (
            f"NOT TRUSTED: none of the {n} patches overlaps another, so nothing was measured: "
            "check their offsets (or give the grid and the overlap)"
        )
        return Verdict(False, line, isolated, loose)
    if isolated:
        line = (
            f"NOT TRUSTED: {len(isolated)} of {n} patches overlap no other "
            f"({listed(isolated, 6)}): their places are their offsets, not a measurement; "
            "check those files' offsets"
        )
        return Verdict(False, line, isolated, loose)
    if 2 * len(loose) > len(linked):
        line = (
            f"NOT TRUSTED: the places of {len(loose)} of {n} patches are not confirmed by "
            f"their overlaps ({listed(loose, 6)}; the warnings say why): the offsets may be "
            "wrong, or the overlaps too narrow or too flat"
        )
        return Verdict(False, line, isolated, loose)
    if not registering:
        return Verdict(True, f"CONFIRMED: Z levelled ({n} patches)", isolated, loose)
    if not loose:
        line = f"CONFIRMED: every patch's place measured by its overlaps ({n} patches)"
        return Verdict(True, line, isolated, loose)
    # most places measured: the mosaic stands, but the few that are not are named, not hidden
    # behind "every" (a corner patch 350 nm off was reported so in its warning alone)
    line = (
        f"CONFIRMED: the places of {n - len(loose)} of {n} patches measured by their overlaps; "
        f"{len(loose)} not confirmed ({listed(loose, 6)}; the warnings say why): "
        "their part of the mosaic lies where the merge left them, not where a measurement did"
    )
    return Verdict(True, line, isolated, loose)
