"""Physics of the simulated AFM-in-SEM, driven through the real procedures and drivers."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from hardware.procedures import CrashError, LandingConfig, NoSurfaceError, acquire_patch, land
from hardware.protocols import ForceLoop, LineRecorder, ProbeSignal
from hardware.sim.instrument import SimulatedAFM, WorldParams
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


def test_a_scan_reproduces_the_surface_within_noise_and_dilation(afm: SimulatedAFM) -> None:
    result = acquire_patch(
        stage_x=afm.stage_x,
        stage_y=afm.stage_y,
        x=afm.robot_x,
        y=afm.robot_y,
        z=afm.robot_z,
        loop=afm,
        probe=afm,
        recorder=afm,
        origin=(1e-6, 2e-6),
        size=(0.6e-6, 0.6e-6),
        pixels=(30, 30),
        line_rate=2.0,
    )
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
