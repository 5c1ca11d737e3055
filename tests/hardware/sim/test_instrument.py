"""Physics of the simulated AFM-in-SEM, driven through the real procedures and drivers."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from hardware.procedures import (
    CrashError,
    LandingConfig,
    NoSurfaceError,
    SaturationError,
    land,
    retract,
)
from hardware.protocols import TRACKING_BOUND, ForceLoop, LineRecorder, ProbeSignal
from hardware.raster import FineRaster
from hardware.sim.faults import LOST_SHARE, Z_JUMP, strike_line
from hardware.sim.instrument import SimulatedAFM, WorldParams
from hardware.sim.mosaic import acquire_on
from hardware.sim.probe import ProbeModel
from hardware.sim.surfaces import FoldedSurface


@pytest.fixture
def afm(folded: FoldedSurface) -> Iterator[SimulatedAFM]:
    with SimulatedAFM(folded, seed=3) as instrument:
        yield instrument


def test_it_fills_the_roles(afm: SimulatedAFM) -> None:
    assert isinstance(afm, ProbeSignal)
    assert isinstance(afm, ForceLoop)
    assert isinstance(afm, LineRecorder)


def test_probe_model() -> None:
    p = ProbeModel()
    d = p.distance_at(10.0)
    assert float(p.delta_f(d)) == pytest.approx(10.0, abs=1e-6)
    assert 1e-9 < d < 4e-9
    assert p.slope(d) < 0  # the repulsive branch: Δf falls with distance
    assert not p.locked(float(p.delta_f(p.crash_distance() - 1e-10)))


def test_landing_stops_at_the_set_point(afm: SimulatedAFM) -> None:
    assert afm.distance(afm.clock.now()) > 1e-6  # starts microns away
    report = land(afm.robot_z, afm, afm, LandingConfig(setpoint=10.0))
    assert report.cycles > 3
    assert afm.engaged()
    assert afm.distance(afm.clock.now()) == pytest.approx(afm.probe.distance_at(10.0), abs=0.5e-9)
    shifts = [afm.frequency_shift() for _ in range(50)]
    assert np.mean(shifts) == pytest.approx(10.0, abs=0.5)


def test_no_surface_within_range(folded: FoldedSurface) -> None:
    with SimulatedAFM(folded, params=WorldParams(z_top=50e-6)) as far:
        with pytest.raises(NoSurfaceError, match="no surface"):
            land(far.robot_z, far, far, LandingConfig(max_cycles=5))
        assert not far.engaged()  # withdrawn: the safe state


def test_a_crash_is_detected(afm: SimulatedAFM) -> None:
    land(afm.robot_z, afm, afm)
    afm.withdraw()
    # drive Z far down in stepping mode with the loop open: the tip hits the surface
    afm.robot_z.step(400, amplitude=4095, frequency=1000)
    afm.robot_z.status()
    with pytest.raises(CrashError):
        land(afm.robot_z, afm, afm)
    assert afm.crashed


def _acquire(afm: SimulatedAFM) -> Any:
    """A 30 x 30 patch of 0.6 µm at (1, 2) µm, through the real procedure."""
    return acquire_on(afm, origin=(1e-6, 2e-6), size=(0.6e-6, 0.6e-6), pixels=(30, 30),
                      line_rate=2.0)  # fmt: skip


def test_a_scan_reproduces_the_surface_within_noise_and_dilation(afm: SimulatedAFM) -> None:
    result = _acquire(afm)
    h = result.lines.heights
    where = np.array(afm.line_positions[-30:])  # where each pixel truly was (simulator truth)
    ideal = afm.surface_height(where[..., 0], where[..., 1], 0.0)  # what a 10 nm tip can touch
    diff = h - ideal
    diff -= np.nanmean(diff, axis=1, keepdims=True)  # set-point distance and drift per line
    # read-out noise, drift within a line, loop tracking, averaging over the pixel
    assert np.nanstd(diff) < 3e-9
    nominal_x = result.origin[0] + np.arange(30) * 2e-8
    assert np.nanmax(np.abs(where[..., 0] - nominal_x)) < 40e-9  # fine-mode hysteresis, creep
    assert not afm.engaged()  # retracted after the patch


def test_drift_grows_with_simulated_time(afm: SimulatedAFM) -> None:
    d0 = np.linalg.norm(afm.drift(0.0))
    d1 = np.linalg.norm(afm.drift(60.0))
    d2 = np.linalg.norm(afm.drift(600.0))
    assert d0 == 0.0 < d1 < d2
    assert d2 == pytest.approx(10 * d1)


def _scan_against_truth(afm: SimulatedAFM) -> tuple[np.ndarray, np.ndarray]:
    """A 30 x 30 scan, and its heights less what a sharp tip touches where each pixel truly
    was (simulator truth), each line's own offset left in."""
    h: np.ndarray = _acquire(afm).lines.heights
    where = np.array(afm.line_positions[-30:])
    return h, h - afm.surface_height(where[..., 0], where[..., 1], 0.0)


@pytest.fixture
def still(folded: FoldedSurface) -> Iterator[SimulatedAFM]:
    """An instrument without drift or charging."""
    params = WorldParams(thermal_xy=0.0, thermal_z=0.0, charging=0.0)
    with SimulatedAFM(folded, seed=3, params=params) as instrument:
        yield instrument


@pytest.mark.filterwarnings("ignore:All-NaN slice:RuntimeWarning")  # the lost lines
@pytest.mark.filterwarnings("ignore:Degrees of freedom:RuntimeWarning")
@pytest.mark.parametrize("kind", ["tip_change", "parachute", "lost_lines", "z_jump"])
def test_a_spoiled_scan_is_spoiled_from_its_strike_line_on_and_the_next_is_clean(
    still: SimulatedAFM, kind: str
) -> None:
    afm = still
    afm.spoil_next_scan(kind, lines=30)
    assert afm.spoiling == kind
    heights, off = _scan_against_truth(afm)
    assert afm.spoiling is None  # one scan only
    k = strike_line(30)
    line = np.nanmedian(off, axis=1)  # per line: the set-point distance (and any jump)
    spread = np.nanstd(off - line[:, None], axis=1)  # within a line: tracking, tip, noise
    # rows are straightened by the Y sensor, which spreads a lost line into its neighbours
    assert np.all(np.isfinite(heights[: k - 1]))
    if kind == "lost_lines":
        assert np.isnan(heights[k : k + round(LOST_SHARE * 30)]).all()
    elif kind == "z_jump":  # the truth is read after the jump: lines before it lie below
        jump = np.median(line[k + 1 :]) - np.median(line[: k - 1])
        assert jump == pytest.approx(Z_JUMP, abs=3e-9)
    else:  # a blunt tip fills valleys, a parachuting loop hangs over steps down
        assert np.median(spread[k + 1 :]) > 3 * np.median(spread[: k - 1])
    clean, off_clean = _scan_against_truth(afm)
    line = np.median(off_clean, axis=1)
    assert np.all(np.isfinite(clean)) and np.ptp(line) < 6e-9
    assert np.std(off_clean - line[:, None]) < 4e-9
    with pytest.raises(ValueError, match="unknown fault"):
        afm.spoil_next_scan("gremlins", lines=30)


def test_each_line_records_how_the_loop_tracked(still: SimulatedAFM) -> None:
    """A clean scan tracks within the bound on every line; a parachuting loop, from its
    strike line on, strays far past it on many lines (the quality gate's record)."""
    afm = still
    clean = _acquire(afm).lines
    assert clean.tracking is not None and clean.saturated is not None
    assert clean.saturated_lines() == 0 and clean.mistracked_lines() == 0
    assert np.all(clean.tracking >= 0) and np.all(clean.tracking < TRACKING_BOUND)
    afm.spoil_next_scan("parachute", lines=30)
    spoiled = _acquire(afm).lines
    k = strike_line(30)
    assert spoiled.mistracked_lines() > 0.05 * 30
    assert spoiled.tracking is not None and np.all(spoiled.tracking[: k - 1] < TRACKING_BOUND)


class _FallingSample:
    """A line recorder under which the sample falls beyond Z's reach after ``after`` lines."""

    def __init__(self, afm: SimulatedAFM, after: int) -> None:
        self.afm, self.after, self.lines = afm, after, 0

    def record_line(self, samples: int, duration: float) -> tuple[np.ndarray, float]:
        self.lines += 1
        if self.lines > self.after:
            self.afm.sample_z = -1.2e-6
        return self.afm.record_line(samples, duration)


def test_lines_with_z_saturated_are_counted_and_a_caller_without_a_gate_stops(
    still: SimulatedAFM,
) -> None:
    afm = still
    raster = FineRaster(afm.robot_x, afm.robot_y, _FallingSample(afm, after=20), afm)
    raster.prepare(size=(0.6e-6, 0.6e-6), pixels=(30, 30))
    land(afm.robot_z, afm, afm)
    try:
        lines = raster.scan(size=(0.6e-6, 0.6e-6), pixels=(30, 30), line_rate=2.0)
    finally:
        retract(afm.robot_z, afm)
    assert lines.saturated is not None
    assert not lines.saturated[:20].any() and lines.saturated[21:].all()
    with pytest.raises(SaturationError, match=r"on (9|10) of 30 lines"):
        lines.require_unsaturated()
