"""The quality gate: keep a patch, or scan it again, and why.

Two witnesses judge a patch. The scan's own record (:class:`ScanRecord`): Z at an end of its
range, the loop's tracking error or lost lines over a share of the lines, the PLL unlocked
during the scan. And the merge's own report (:class:`~merge.live.LiveUpdate`): overlaps with
texture on both sides that did not register, or residuals far above those of the mosaic's
other patches (a tip change, a parachuting loop, a Z jump leave a patch that no rigid motion
with a drift plane lays onto its neighbours).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from merge.live.incremental import LiveUpdate
from merge.report.misfit import PairMisfit

#: A share of lines above this, saturated or lost, spoils a patch.
LINE_SHARE = 0.05
#: A share of lines above this with the loop off the surface spoils a patch. A coarse scan
#: may briefly parachute past a step down on a line or two in ten (physics, not a fault); a
#: loop that lost the surface does it on most lines after the fault.
MISTRACKED_SHARE = 0.3
#: A pair's residual RMS above this many times the mosaic's usual (the median over the pairs
#: of the patches passed, and at least the noise of two overlapping scans) is a bad pair.
RESIDUAL_FACTOR = 2.5
#: A step between a patch's lines over a neighbour is a Z jump when it stands this many
#: standard errors out (straight scans: at most 6) ...
STEP_SIGMAS = 10.0
#: ... and is this many times the usual misfit high.
STEP_FACTOR = 2.0
#: Pairs with fewer points than this (a corner's overlap) are not judged.
MIN_PAIR_POINTS = 64
#: A patch's lines count as seen to lie well when good pairs spanned this share of them.
SEEN_SHARE = 0.8

#: An area of the mosaic, ``(xmin, ymin, xmax, ymax)``, metres.
Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class ScanRecord:
    """What the instrument recorded of one patch's scan: counts of its ``lines``."""

    lines: int
    saturated: int = 0
    mistracked: int = 0
    lost: int = 0
    pll_unlocked: bool = False

    def __post_init__(self) -> None:
        if self.lines < 1:
            raise ValueError(f"a scan has at least one line, got {self.lines}")
        for name in ("saturated", "mistracked", "lost"):
            value = getattr(self, name)
            if not 0 <= value <= self.lines:
                raise ValueError(f"{name} must be within 0..{self.lines} lines, got {value}")


@dataclass(frozen=True)
class Verdict:
    """``ok``, or why not (``reason``, for the operator and the run's record)."""

    ok: bool
    reason: str = ""


class Gate:
    """Judges every addition to a live merge against the mosaic's usual misfit.

    It learns the usual from the patches it passes: the median RMS of their pairs, and the
    median of their noise (two overlapping scans of that noise differ by ``sqrt(2)`` of it).
    A pair that lies badly is blamed on one of its two patches:

    * on the patch added, if the other was already seen to lie well on the scan lines where
      the two overlap (good pairs of its own spanned that stretch of Y: a fault strikes from
      a line on), or if its own other pairs do not vouch for those lines either;
    * else on the older patch: its lines that lie badly were not seen before (they had no
      neighbour yet), and the new patch's other pairs saw its own lines there lie well;
    * a re-scan that lies badly over the same neighbour as the scan it replaced turns the
      blame on that neighbour: two scans agree, the neighbour is the odd one.

    Pure: it holds numbers, and touches nothing.
    """

    def __init__(self) -> None:
        self._pair_rms: list[float] = []
        self._noise: list[float] = []
        #: per patch id, the areas (boxes) of the mosaic where good pairs saw it lie well
        self._seen_well: dict[str, list[Box]] = {}
        #: per patch id, the neighbours its failed scans lay badly over
        self._failed_over: dict[str, set[str]] = {}

    @property
    def usual(self) -> float:
        """The misfit of a good pair, metres: the median of the passed pairs' RMS, at least
        ``sqrt(2)`` times the median noise (NaN before the first pair)."""
        floor = math.sqrt(2.0) * float(np.median(self._noise)) if self._noise else 0.0
        seen = float(np.median(self._pair_rms)) if self._pair_rms else math.nan
        return max(seen, floor) if math.isfinite(seen) else math.nan

    def forget(self, patch_id: str) -> None:
        """Patch ``patch_id`` left the mosaic (to be scanned again): what was seen of it goes."""
        self._seen_well.pop(patch_id, None)

    def judge(
        self, update: LiveUpdate, *, noise: float, record: ScanRecord | None = None
    ) -> dict[str, Verdict]:
        """Verdicts on an addition: always one for the patch added (``update.id``), and one
        for every older neighbour the misfits blame instead.

        Parameters
        ----------
        update : LiveUpdate
            What :meth:`merge.live.LiveMerge.add` returned for the patch.
        noise : float, keyword-only
            The patch's height noise, metres (:func:`merge.core.noise.estimate_noise`).
        record : ScanRecord, keyword-only
            What the scan recorded of itself, if known.
        """
        c = update.id
        if record is not None:
            said = record_verdict(record)
            if not said.ok:
                return {c: said}
        if update.measurable and not update.registered:
            reason = "its overlaps have texture but did not register with its neighbours"
            return {c: Verdict(False, reason)}
        pairs = {j: m for j, m in update.misfits.items() if m.points >= MIN_PAIR_POINTS}
        usual = self.usual
        bad = {j: why for j, m in pairs.items() if (why := _misfit(m, usual))}
        verdicts = self._blame(c, pairs, bad)
        if verdicts[c].ok:
            self._pass(c, pairs, bad, noise)
        else:
            self._failed_over.setdefault(c, set()).update(bad)
        return verdicts

    def final(self, misfits: dict[str, dict[str, PairMisfit]]) -> dict[str, Verdict]:
        """The last look at the whole mosaic, every neighbour there: ``misfits`` says how each
        patch lies over each of its own (:meth:`merge.live.LiveMerge.misfits_of`, by id).
        Every patch that lies badly over at least two neighbours, more of them than any of
        those lies badly over, fails (it is what the bad pairs share); the others pass. A
        spoiled patch whose spoiled lines met only later patches, each of which lies well
        over the rest, is caught here."""
        usual = self.usual
        bad: dict[str, dict[str, str]] = {}
        for c, pairs in misfits.items():
            judged = {j: m for j, m in pairs.items() if m.points >= MIN_PAIR_POINTS}
            bad[c] = {j: why for j, m in judged.items() if (why := _misfit(m, usual))}
        verdicts = {}
        for c, mine in bad.items():
            count = len(mine)
            if count >= 2 and all(len(bad.get(j, {})) < count for j in mine):
                worst = max(mine, key=lambda j: misfits[c][j].rms)
                reason = f"over {count} of its neighbours, e.g. {worst}: {mine[worst]}"
                verdicts[c] = Verdict(False, reason)
            else:
                verdicts[c] = Verdict(True)
        return verdicts

    def _blame(
        self, c: str, pairs: dict[str, PairMisfit], bad: dict[str, str]
    ) -> dict[str, Verdict]:
        """Who of each bad pair is to blame (see the class's rules)."""
        verdicts = {c: Verdict(True)}
        if not bad:
            return verdicts
        again = self._failed_over.get(c, set()) & set(bad)
        vouched = [m.box for j, m in pairs.items() if j not in bad]
        against_c = [
            j
            for j in bad
            if j not in again
            and (
                _covers(self._seen_well.get(j, []), pairs[j].box)
                or not _covers(vouched, pairs[j].box)
            )
        ]
        if against_c:
            worst = max(against_c, key=lambda j: pairs[j].rms)
            verdicts[c] = Verdict(False, f"over {worst}: {bad[worst]}")
            return verdicts
        for j, why in bad.items():
            verdicts[j] = Verdict(False, f"under the later patch {c}: {why}")
        return verdicts

    def _pass(
        self, c: str, pairs: dict[str, PairMisfit], bad: dict[str, str], noise: float
    ) -> None:
        """Learn from a patch that passed: its good pairs' misfits, its noise, and where it and
        its neighbours were seen to lie well."""
        for j, m in pairs.items():
            if j in bad:
                continue
            self._pair_rms.append(m.rms)
            self._seen_well.setdefault(c, []).append(m.box)
            self._seen_well.setdefault(j, []).append(m.box)
        if math.isfinite(noise):
            self._noise.append(noise)


def _misfit(m: PairMisfit, usual: float) -> str:
    """Why one pair lies badly (empty: it does not), against the usual misfit ``usual``."""
    if not math.isfinite(usual) or usual <= 0:
        return ""
    if m.rms > RESIDUAL_FACTOR * usual:
        return (
            f"residual RMS {m.rms * 1e9:.2f} nm, over {RESIDUAL_FACTOR:g} x the mosaic's usual "
            f"{usual * 1e9:.2f} nm"
        )
    step = m.step
    if step.significance > STEP_SIGMAS and abs(step.height) > STEP_FACTOR * usual:
        height = step.height * 1e9
        return f"a Z step of {height:.1f} nm between its lines {step.line - 1} and {step.line}"
    return ""


def record_verdict(record: ScanRecord, *, tracking: bool = True) -> Verdict:
    """The scan record's own witness (it needs no merge: the acquisition may act on it at
    once); with ``tracking`` false, the loop's tracking is left out (the unambiguous signs of
    the instrument's state only: the PLL, lines lost, Z saturated)."""
    if record.pll_unlocked:
        return Verdict(False, "the PLL lost the resonance during the scan")
    for count, share, what in (
        (record.lost, LINE_SHARE, "lost"),
        (record.saturated, LINE_SHARE, "with Z at a limit of its range"),
        (record.mistracked if tracking else 0, MISTRACKED_SHARE, "with the loop off the surface"),
    ):
        if count > share * record.lines:
            return Verdict(False, f"{count} of {record.lines} lines {what}")
    return Verdict(True)


def _covers(boxes: list[Box], box: Box) -> bool:
    """Whether the Y stretches of ``boxes`` cover most of ``box``'s (a fault strikes from a
    scan line on, in time, and scan lines run along X: lines seen to lie well are good)."""
    lo, hi = box[1], box[3]
    covered = 0.0
    for a, b in _joined([(s[1], s[3]) for s in boxes]):
        covered += max(0.0, min(b, hi) - max(a, lo))
    return covered >= SEEN_SHARE * max(hi - lo, 1e-12)


def _joined(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """``spans`` with the overlapping ones joined."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
