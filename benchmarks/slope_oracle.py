"""What the merge would reach if it knew the surface's slopes: the default merge on draws of a
case as it is, and again with an oracle's slopes in its Jacobian.

A registration step solves ``Σ J r = 0``, ``J`` made of the surface's slopes under every row's
point. The merge takes them from the scans (the destination's look-up, a pixel either side),
whose noise and blur on a roughness at the pixel's scale (a grating's flat faces at the paper's
grid: 1.5 nm at 25 nm under 20 nm pixels) cost precision: a step's variance grows by the
inverse of ``(Σ J g)² / (Σ J² Σ g²)`` against the true slopes ``g``. The oracle hands the
raw level's rows on the flat faces (slopes under :data:`merge.refine.source_slopes.FLAT`) the
true surface's own gradient at their point, which no estimator has; what is left is the noise
of the heights themselves. On the grating sweep's draw 0, the worst draw of nearly every
paper-grid case, it tells whether any merge could bring that draw within a target.

Run: ``python benchmarks/slope_oracle.py [--cases paper-r200-p3-s0.6] [--draws 10]``
(about 5 s a draw; the cases as ``crb.py`` names them).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from bench_cases import floor_of, scored_merge  # modules beside this script
from crb import chosen_cases
from numpy.typing import NDArray

import merge.refine.normal_system as normal_system
from backend.synthetic import patch_set_from_synth
from merge import run
from merge.refine.bank import SurfaceBank
from merge.refine.rows import PatchState, feet
from merge.refine.runs import RowBlock
from merge.refine.source_slopes import FLAT

if TYPE_CHECKING:
    from hardware.sim.surfaces import Surface
    from hardware.sim.synth import SynthPatch

FloatArray = NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[1]
#: Step (m) of the central differences that take the true surface's gradient.
EPS = 0.05e-9


def true_slopes(
    bank: SurfaceBank,
    rows: RowBlock,
    state: PatchState,
    synth: Sequence[SynthPatch],
    surface: Surface,
) -> FloatArray:
    """(m, 2) the true surface's slopes under every row's point, in its destination's frame and
    drift plane (as the merge's look-ups give them); the bank's patches are ``synth``'s, in
    order."""
    if len(bank.centre) != len(synth):
        raise ValueError(f"the bank holds {len(bank.centre)} patches, the truth {len(synth)}")
    _, p_dst, _ = feet(bank, rows, state)
    dst = rows.dst
    scale = np.array([s.pixel_size[0] for s in synth]) / bank.dx
    # nominal XY of every point (the bank's frames are centred on their patches)
    nominal = (p_dst[:, :2] + bank.centre[dst, :2]) * scale[dst, None]
    R = np.array([s.rotation[:2, :2] for s in synth])[dst]
    t = np.array([s.translation[:2] for s in synth])[dst]
    world = np.einsum("mij,mj->mi", R, nominal) + t
    x, y = world[:, 0], world[:, 1]
    gx = (surface.height(x + EPS, y) - surface.height(x - EPS, y)) / (2 * EPS)
    gy = (surface.height(x, y + EPS) - surface.height(x, y - EPS)) / (2 * EPS)
    # a gradient turns with its patch: into the destination's frame
    local = np.einsum("mji,mj->mi", R, np.column_stack([gx, gy]))
    out: FloatArray = local + state.slope[dst]
    return out


@contextlib.contextmanager
def oracle_slopes(synth: Sequence[SynthPatch], surface: Surface) -> Iterator[None]:
    """Within this block, the raw level's rows on flat faces take :func:`true_slopes`."""
    # the build's own name for the rows' residuals and slopes (it imported the function)
    names = vars(normal_system)
    own = names["residuals"]

    def told(
        bank: SurfaceBank, rows: RowBlock, state: PatchState
    ) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, NDArray[np.bool_]]:
        r, ok, grad, smoothed = own(bank, rows, state)
        if bank.nodes > 1:  # the raw heights' spline: the raw level
            exact = true_slopes(bank, rows, state, synth, surface)
            flat = ok & (np.sum(exact**2, axis=1) < FLAT**2)
            grad[flat] = exact[flat]
        return r, ok, grad, smoothed

    names["residuals"] = told
    try:
        yield
    finally:
        names["residuals"] = own


def merged(synth: list[SynthPatch], surface: Surface) -> tuple[float, float]:
    """The default merge of ``synth``: map error over the floor, XY registration error (nm)."""
    result = run(patch_set_from_synth(synth))
    by_id = {p.id: p.transform for p in result.patches}
    score, error = scored_merge(synth, [by_id[s.id] for s in synth], result.mosaic, surface)
    return error / floor_of(synth, surface), score.xy * 1e9


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="paper-r200-p3-s0.6,paper-r200-p3-s0.3")
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument(
        "--json", default=str(ROOT / "benchmarks" / "results" / "slope_oracle.json")
    )
    args = parser.parse_args(argv)
    if args.draws < 1:
        parser.error(f"--draws must be at least 1, got {args.draws}")
    try:
        cases = chosen_cases(args.cases, 0)
    except ValueError as e:
        parser.error(str(e))
    print(f"{'case':<22}{'':>9}{'map/floor median':>18}{'worst':>8}{'XY nm RMS':>11}   per draw")
    rows: list[dict[str, Any]] = []
    for first in cases:
        name = first.name
        runs: dict[str, list[tuple[float, float]]] = {"merge": [], "oracle": []}
        for k in range(args.draws):
            surface, synth = first.redrawn(k).synthesize()
            runs["merge"].append(merged(synth, surface))
            with oracle_slopes(synth, surface):
                runs["oracle"].append(merged(synth, surface))
        for label, values in runs.items():
            ratio, xy = np.array(values).T
            row = {
                "case": name,
                "slopes": label,
                "map_over_floor": ratio.tolist(),
                "reg_xy_nm": xy.tolist(),
                "map_over_floor_median": float(np.median(ratio)),
                "map_over_floor_worst": float(ratio.max()),
                "reg_xy_nm_rms": float(np.sqrt(np.mean(xy**2))),
            }
            rows.append(row)
            print(
                f"{name if label == 'merge' else '':<22}{label:>9}"
                f"{row['map_over_floor_median']:>18.3f}{row['map_over_floor_worst']:>8.3f}"
                f"{row['reg_xy_nm_rms']:>11.3f}   " + " ".join(f"{v:.2f}" for v in ratio),
                flush=True,
            )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
