"""The planner's scan limits against the simulated instrument: over pixels per line, line
rates and samples, nothing the planner accepts crashes the tip, and the refusals name the
limit. The simulator's force loop runs in time, so finer lines track as well as coarse ones."""

from __future__ import annotations

import numpy as np
import pytest

from backend.acquisition.planner import InstrumentLimits, PatchSpec, PlanError, check_scan
from hardware.protocols import ScanLines
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.mosaic import acquire_on
from hardware.sim.surfaces import surface_by_name

SIZE = 1.6e-6  # the fine range: the widest, fastest patch


@pytest.fixture(scope="module", params=["folded", "chessboard"])
def sample(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def _scan(afm: SimulatedAFM, pixels: tuple[int, int], rate: float) -> ScanLines:
    # over an edge of the chessboard, a fold of the other
    return acquire_on(afm, origin=(0.2e-6, 0.5e-6), size=(SIZE, SIZE), pixels=pixels,
                      line_rate=rate).lines  # fmt: skip


def _refusal(patch: PatchSpec, rate: float, limits: InstrumentLimits) -> PlanError | None:
    try:
        check_scan(patch, rate, limits)
    except PlanError as refused:
        return refused
    return None


@pytest.mark.slow
@pytest.mark.parametrize("per_line", [16, 64, 256, 512])
@pytest.mark.parametrize("rate", [0.1, 0.5, 2.0, 5.0])
def test_what_the_planner_accepts_never_crashes(sample: str, per_line: int, rate: float) -> None:
    with SimulatedAFM(surface_by_name(sample), seed=7) as afm:
        limits = InstrumentLimits(scan=afm.scan_envelope())
        lines = min(per_line, 64)
        patch = PatchSpec(SIZE, SIZE, (per_line, lines))
        refused = _refusal(patch, rate, limits)
        if refused is not None:
            assert refused.field == "line_rate" and "lines/s" in str(refused)
            return
        scanned = _scan(afm, (per_line, lines), rate)  # a crash raises here
        assert not afm.crashed and np.isfinite(scanned.heights).all()


def test_the_fastest_accepted_speed_is_refused_a_little_above(sample: str) -> None:
    with SimulatedAFM(surface_by_name(sample), seed=7) as afm:
        envelope = afm.scan_envelope()
        limits = InstrumentLimits(scan=envelope)
        fastest = envelope.max_speed / SIZE  # lines per second
        check_scan(PatchSpec(SIZE, SIZE, (64, 32)), 0.99 * fastest, limits)
        with pytest.raises(PlanError, match="force loop"):
            check_scan(PatchSpec(SIZE, SIZE, (64, 32)), 1.01 * fastest, limits)


def test_finer_lines_at_the_same_rate_track_as_well() -> None:
    with SimulatedAFM(surface_by_name("folded"), seed=7) as afm:
        coarse = _scan(afm, (64, 16), 1.0)
        fine = _scan(afm, (512, 16), 1.0)
    assert coarse.tracking is not None and fine.tracking is not None
    # the same loop in time: what it held is the same to within the noise of a line
    assert np.median(fine.tracking) <= 1.15 * np.median(coarse.tracking)
