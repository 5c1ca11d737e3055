"""What an efficient merge could reach: the Cramér-Rao bound of a synthetic patch set
(:mod:`cramer_rao`), against the merge.

Beside it (``--noise-draws N``), the merge itself on N draws of the noise over the case's own
surface, geometry and drift: whether it is efficient shows in the two distributions of the
map error over the floor (median, 90th percentile, largest), and a single draw far out is then
the noise's, not the method's.

The cases are the bench's (:data:`bench_cases.CASES`) or the grating sweep's by name
(``paper-r200-p3-s0.6``; :func:`bench_cases.grating_cases`), on their first draw of texture,
drift and noise or on ``--draw K``: the sweep's worst draws can be put beside what the noise alone
spreads over the same geometry.

Run: ``python benchmarks/crb.py [--cases tgx1,folded] [--draw K] [--samples 32]
[--noise-draws 16]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from cramer_rao import efficient_errors, rms_nm, spread_of  # a module beside this script
from numpy.typing import NDArray

from backend.synthetic import patch_set_from_synth
from merge import run

if TYPE_CHECKING:
    from bench_cases import Case

    from hardware.sim.surfaces import Surface
    from hardware.sim.synth import SynthPatch

FloatArray = NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[1]


def merge_over_noise(case: Case, draws: int, *, seed: int = 0) -> dict[str, float]:
    """The default merge on ``draws`` draws of the noise (white and per line) over the case's
    surface, geometry and drift: registration errors (nm, RMS over the draws) and the spread
    of the map error over each draw's floor; beside them the map error over the floor on the
    case's own noise (``map_over_floor_own``), the draw a bench or sweep scores."""
    still = dataclasses.replace(
        case, drift=dataclasses.replace(case.drift, noise=0.0, line_noise=0.0)
    )
    surface, clean = still.synthesize()
    rng = np.random.default_rng(seed)
    xy, z, ratio = [], [], []
    for _ in range(draws):
        synth = [
            dataclasses.replace(
                s,
                heights=s.heights
                + rng.normal(0.0, case.drift.line_noise, (s.heights.shape[0], 1))
                + rng.normal(0.0, case.drift.noise, s.heights.shape),
            )
            for s in clean
        ]
        exy, ez, r = _merged(synth, surface)
        xy.append(exy)
        z.append(ez)
        ratio.append(r)
    own = _merged(case.synthesize()[1], surface)[2]
    return {
        "reg_xy_nm": rms_nm(xy),
        "reg_z_nm": rms_nm(z),
        **spread_of(np.array(ratio)),
        "map_over_floor_own": own,
    }


def _merged(synth: list[SynthPatch], surface: Surface) -> tuple[float, float, float]:
    """The default merge of ``synth``: XY and Z registration errors (m) and the map error over
    the floor."""
    from bench_cases import floor_of, scored_merge

    result = run(patch_set_from_synth(synth))
    by_id = {p.id: p.transform for p in result.patches}
    score, error = scored_merge(synth, [by_id[s.id] for s in synth], result.mosaic, surface)
    return score.xy, score.z, error / floor_of(synth, surface)


def chosen_cases(names: str, draw: int) -> list[Case]:
    """The bench's and the grating sweep's cases named in ``names`` (comma-separated), in that
    order, each on its ``draw``-th draw; ``ValueError`` names what is unknown."""
    from bench_cases import CASES, grating_cases

    known = {c.name: c for c in CASES} | {c.name: c for *_, c in grating_cases()}
    wanted = [n for n in names.split(",") if n]
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ValueError(f"unknown cases {', '.join(unknown)}: use {', '.join(known)}")
    return [known[n].redrawn(draw) for n in wanted]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="tgx1,folded,tgx1-harsh,folded-harsh,mos2-real")
    parser.add_argument(
        "--draw", type=int, default=0, help="the cases' draw of texture, drift and noise"
    )
    parser.add_argument("--samples", type=int, default=32)
    parser.add_argument(
        "--noise-draws", type=int, default=0, help="also merge this many draws of the noise"
    )
    parser.add_argument("--json", default=str(ROOT / "benchmarks" / "results" / "crb.json"))
    args = parser.parse_args(argv)
    try:
        cases = chosen_cases(args.cases, args.draw)
    except ValueError as e:
        parser.error(str(e))
    rows: list[dict[str, Any]] = []
    head = f"{'case':<20}{'CRB XY nm':>10}{'CRB Z nm':>10}{'CRB map':>9}{'floor':>8}"
    spread = "map/floor med / p90 / max"
    print(
        head
        + f"{'CRB/floor':>11}   {'CRB ' + spread:<31}"
        + (f"merge {spread}, XY nm; own draw" if args.noise_draws else "")
    )
    for case in cases:
        surface, synth = case.synthesize()
        r = efficient_errors(synth, surface, case.drift, samples=args.samples)
        floor = r["floor_nm"]
        row: dict[str, Any] = {"case": case.name, "draw": args.draw, **r}
        line = (
            f"{case.name:<20}{r['reg_xy_nm']:>10.2f}{r['reg_z_nm']:>10.2f}{r['map_nm']:>9.2f}"
            f"{floor:>8.2f}{r['map_nm'] / floor:>11.2f}   {_spread_text(r):<31}"
        )
        if args.noise_draws:
            m = merge_over_noise(case, args.noise_draws)
            row["merge"] = {"draws": args.noise_draws, **m}
            line += f"{_spread_text(m)}, {m['reg_xy_nm']:.2f}; {m['map_over_floor_own']:.2f}"
        rows.append(row)
        print(line, flush=True)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    print(f"\nwrote {args.json}")
    return 0


def _spread_text(r: dict[str, float]) -> str:
    keys = ("map_over_floor_median", "map_over_floor_p90", "map_over_floor_max")
    return " / ".join(f"{r[k]:.2f}" for k in keys)


if __name__ == "__main__":
    sys.exit(main())
