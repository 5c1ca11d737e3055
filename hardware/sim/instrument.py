"""The simulated AFM-in-SEM: one world in simulated time, driven through the real drivers.

Geometry (metres). The sample is a :class:`~hardware.sim.surfaces.Surface` in sample (stage)
coordinates, carried by the sample holder (two MCS channels, X and Y): a sample point ``p``
sits at lab position ``p + S``. The probe robot (three MCS channels) holds the tip at lab XY
``T`` (its fine mode rasters) and its Z axis lowers the tip as it extends. So the sample point
under the tip is ``T - S`` plus the thermal drift, and the tip-sample distance is the tip
height minus the surface (dilated by the tip's radius) minus the Z drift.

What the control software sees goes through :class:`~hardware.smaract_mcs.MCSController` over
``socket://`` links to :class:`~hardware.sim.mcs_server.MCSServer`; the physics reads the
simulated channels directly. The force loop is the analogue Z loop of the AFM controller: it
drives the robot Z fine level from the frequency shift, with a finite bandwidth, so steep
edges and fast scans show tracking error (:mod:`hardware.sim.force_loop`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hardware.envelope import ScanEnvelope
from hardware.errors import CrashError, ProcedureError
from hardware.mcs_axis import STAGE_TRAVEL, FineCalibration, MCSAxis
from hardware.procedures import LandingConfig
from hardware.sim.clock import SimClock
from hardware.sim.faults import BLUNT_TIP, Z_JUMP, ArmedFault
from hardware.sim.force_loop import PARACHUTE_RATE, SLEW_RATE, Loop, follow_line
from hardware.sim.mcs_channel import ChannelParams
from hardware.sim.mcs_device import MCSDevice
from hardware.sim.mcs_server import MCSServer
from hardware.sim.probe import ProbeModel
from hardware.sim.relief import patch_relief, steepest_slope
from hardware.sim.surfaces import Surface
from hardware.sim.tip import apex_height
from hardware.smaract_mcs import MCSController

FloatArray = NDArray[np.float64]

#: The drift's largest rate, in its typical rates (``WorldParams.thermal_*``): its spec.
DRIFT_SPREAD = 2.0
#: The share of the set-point's clearance a scan may spend on the loop's lag.
ENVELOPE_SHARE = 0.85
#: Largest spacing of the force loop's knots along a line, metres.
KNOT_SPACING = 4e-9


@dataclass(frozen=True)
class WorldParams:
    """Drift, noise and tip of the simulated world (SI units)."""

    thermal_xy: float = 2e-9 / 60  # m/s per axis (nm per minute)
    thermal_z: float = 30e-9 / 60
    charging: float = 4.0  # Hz: SEM charging shifts Δf towards this, saturating
    charging_time: float = 600.0  # s: time constant of the charging
    tip_radius: float = 10e-9
    z_top: float = 5e-6  # tip height (lab) with Z fully retracted
    loop_bandwidth: float = 3000.0  # Hz: an FM-AFM Z loop's
    z_noise: float = 0.3e-9  # noise of the recorded height (Z read-out), m
    substeps: int = 4  # force-loop knots per pixel, at least


class SimulatedAFM:
    """The instrument: MCS servers and drivers, probe, force loop, line recorder, drift.

    Parameters
    ----------
    surface : Surface
        The sample, in sample coordinates.
    clock : SimClock
        Simulated time (default: as fast as possible).
    params : WorldParams
    probe : ProbeModel
    seed : int
        Seed of the drift directions, noise and channel physics.
    """

    def __init__(
        self,
        surface: Surface,
        *,
        clock: SimClock | None = None,
        params: WorldParams | None = None,
        probe: ProbeModel | None = None,
        seed: int = 0,
        stage_port: int = 0,
        host: str = "127.0.0.1",
    ) -> None:
        self.surface = surface
        self.clock = clock or SimClock(None)
        self.params = params or WorldParams()
        self.probe = probe or ProbeModel()
        self.rng = np.random.default_rng(seed)
        # the sample stage's sensors: scale error and encoder periodic error (tens of nm)
        self.stage_device = MCSDevice(
            channels=2,
            seed=seed + 1,
            params=ChannelParams(sensor_scale_error=3e-3, sensor_periodic_error=25e-9),
        )
        self.robot_device = MCSDevice(channels=3, seed=seed + 2)
        self.stage_server = MCSServer(
            self.stage_device, clock=self.clock, host=host, port=stage_port
        ).start()
        self.robot_server = MCSServer(self.robot_device, clock=self.clock).start()
        self.stage = MCSController.open(self.stage_server.url)
        self.robot = MCSController.open(self.robot_server.url)
        self.stage_x = MCSAxis(self.stage, 0, name="stage x", travel=STAGE_TRAVEL)
        self.stage_y = MCSAxis(self.stage, 1, name="stage y", travel=STAGE_TRAVEL)
        self.robot_x = MCSAxis(self.robot, 0, name="robot x", calibration=FineCalibration(1.6e-6))
        self.robot_y = MCSAxis(self.robot, 1, name="robot y", calibration=FineCalibration(1.6e-6))
        self.robot_z = MCSAxis(self.robot, 2, name="robot z", calibration=FineCalibration(1.6e-6))
        # the drift's rate within the instrument's specification (twice the typical rate)
        direction = np.clip(self.rng.normal(size=3), -DRIFT_SPREAD, DRIFT_SPREAD)
        self._drift_v = np.array(
            [
                self.params.thermal_xy * direction[0],
                self.params.thermal_xy * direction[1],
                self.params.thermal_z * direction[2],
            ]
        )
        self._setpoint: float | None = None
        self._saturated = False
        self._tracking = 0.0
        self.crashed = False
        #: the PLL has lost the resonance (an injected fault): no amplitude, no lock
        self.pll_lost = False
        self.beam_on = True
        #: height of the sample holder, metres: lower it far to take the sample out of reach
        self.sample_z = 0.0
        #: where every sample of every recorded line truly was (simulator-only truth)
        self.line_positions: list[FloatArray] = []
        #: the fault armed for the next scan (:meth:`spoil_next_scan`), if any
        self._spoiling: ArmedFault | None = None
        self._slew_rate = SLEW_RATE
        self._envelope: ScanEnvelope | None = None
        #: a jump of the sample armed for the middle of the next line, metres
        self._jump = 0.0

    # -- lifecycle --------------------------------------------------------------------------

    def close(self) -> None:
        self.stage.close()
        self.robot.close()
        self.stage_server.stop()
        self.robot_server.stop()

    def __enter__(self) -> SimulatedAFM:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def scan_envelope(self) -> ScanEnvelope:
        """What a scan may ask of this instrument on this sample (measured once): the loop's
        bandwidth, the set-point's clearance, the sample's steepest slope and relief within
        a fine range, the drift's specified rate and Z's range."""
        if self._envelope is None:
            z = self.robot_device.axes[2].params.fine_range
            clearance = self.probe.distance_at(LandingConfig().setpoint) - (
                self.probe.crash_distance()
            )
            self._envelope = ScanEnvelope(
                loop_bandwidth=self.params.loop_bandwidth,
                tracking_margin=ENVELOPE_SHARE * clearance,
                sample_slope=steepest_slope(self.surface),
                sample_relief=patch_relief(self.surface, z),
                z_drift=DRIFT_SPREAD * self.params.thermal_z,
                z_range=z,
            )
        return self._envelope

    def jump_next_line(self, height: float) -> None:
        """The sample jumps ``height`` metres up in the middle of the next line recorded (the
        holder slips, or a particle under the tip), and stays there: a step no loop follows,
        so the tip crashes into it (the crash an operator must see handled)."""
        self._jump = height

    def change_tip(self) -> None:
        """A new probe mounted (after a crash): its tip whole, the loop open, Z retracted."""
        self.crashed = False
        self.withdraw()

    # -- physics (the simulator's view; the software never calls these) ----------------------

    def drift(self, t: float) -> FloatArray:
        """Thermal drift of the sample under the tip at time ``t``: (dx, dy, dz) metres."""
        out: FloatArray = self._drift_v * t
        return out

    @property
    def stage_sensor_scale(self) -> float:
        """How the sample stage's sensors scale a true length (1 + their scale error)."""
        return 1.0 + self.stage_device.params.sensor_scale_error

    def stage_position(self) -> tuple[float, float]:
        """Where the sample stage truly is now (x, y metres): a lab point shows the sample
        point this far behind it (what the SEM sees move)."""
        t = self.clock.now()
        sx, sy = (ch.true_position(t) for ch in self.stage_device.axes)
        return sx, sy

    def sample_xy(self, t: float) -> tuple[float, float]:
        """Sample coordinates under the tip at ``t``."""
        sx, sy = (ch.true_position(t) for ch in self.stage_device.axes)
        tx, ty = (ch.true_position(t) for ch in self.robot_device.axes[:2])
        d = self.drift(t)
        return tx - sx + d[0], ty - sy + d[1]

    def tip_height(self, t: float) -> float:
        """Lab height of the tip apex: it goes down as the Z axis extends."""
        return self.params.z_top - self.robot_device.axes[2].true_position(t)

    def surface_height(self, x: FloatArray, y: FloatArray, t: float) -> FloatArray:
        """Surface under a tip of finite radius (its apex rides on the highest nearby point)."""
        top = apex_height(self.surface, x, y, self.params.tip_radius)
        out: FloatArray = top + self.drift(t)[2] + self.sample_z
        return out

    def true_heights(
        self, x0: float, y0: float, shape: tuple[int, int], pixel: float, *, tip: bool = False
    ) -> FloatArray:
        """The sample's true heights (no drift or noise) on a grid: ``shape`` = (ny, nx)
        points from ``(x0, y0)`` every ``pixel`` metres, sample frame. With ``tip``, as the
        tip's apex would ride over it (dilated by the tip): what a perfect AFM would record."""
        ny, nx = shape
        xx, yy = np.meshgrid(x0 + pixel * np.arange(nx), y0 + pixel * np.arange(ny))
        if not tip:
            out: FloatArray = np.asarray(self.surface.height(xx, yy), dtype=np.float64)
            return out
        r = self.params.tip_radius  # row by row: 17 surface points per grid point
        rows = [apex_height(self.surface, xx[k], yy[k], r) for k in range(ny)]
        dilated: FloatArray = np.asarray(rows, dtype=np.float64)
        return dilated

    def distance(self, t: float) -> float:
        x, y = self.sample_xy(t)
        h = float(self.surface_height(np.array([x]), np.array([y]), t)[0])
        return self.tip_height(t) - h

    def charging_offset(self, t: float) -> float:
        """Δf offset from charging by the electron beam: builds up and saturates."""
        if not self.beam_on:
            return 0.0
        return self.params.charging * (1.0 - math.exp(-t / self.params.charging_time))

    # -- ProbeSignal ------------------------------------------------------------------------

    def frequency_shift(self) -> float:
        if self.pll_lost:  # an unlocked PLL sits at the end of its range
            return self.probe.pll_range
        t = self.clock.now()
        d = self.distance(t)
        df = float(self.probe.delta_f(d)) + self.charging_offset(t)
        df += float(self.rng.normal(0.0, self.probe.noise))
        if not self.probe.locked(df):
            self.crashed = self.crashed or d < 0
        return df

    def amplitude(self) -> float:
        return self.probe.amplitude if not (self.crashed or self.pll_lost) else 0.0

    def locked(self) -> bool:
        if self.crashed or self.pll_lost:
            return False
        return self.probe.locked(self.frequency_shift())

    # -- ForceLoop --------------------------------------------------------------------------

    def engage(self, setpoint: float) -> None:
        """Close the Z loop on ``setpoint`` Hz; it settles within a few loop time constants."""
        self._setpoint = setpoint
        self.clock.advance(5.0 / self.params.loop_bandwidth)
        self._settle_loop(self.clock.now())

    def withdraw(self) -> None:
        """Open the loop and retract Z fully in fine mode."""
        self._setpoint = None
        self._saturated = False
        t = self.clock.now()
        self.robot_device.axes[2].drive_level(0, t)

    def engaged(self) -> bool:
        return self._setpoint is not None

    @property
    def setpoint(self) -> float | None:
        """The set-point the loop regulates on, Hz (None when open)."""
        return self._setpoint

    def hold(self) -> None:
        """Open the loop and leave Z where it is (a controller switched off, not withdrawn)."""
        self._setpoint = None
        self._saturated = False

    def track(self) -> None:
        """The engaged loop follows the surface (and the drift) up to now."""
        if self._setpoint is not None:
            self._settle_loop(self.clock.now())

    def saturated(self) -> bool:
        return self._saturated

    def tracking_error(self) -> float:
        """The loop's error over the last line recorded, metres: the tip's distance from the
        set-point's after each update (what the loop could not follow), as the size it kept
        for a quarter of the line (a step edge's brief lag does not count, a tip that lost
        the surface does)."""
        return self._tracking

    def _required_extension(self, height: FloatArray | float, t: float) -> FloatArray:
        """Fine Z extension that puts the tip at the set-point distance above ``height``."""
        z = self.robot_device.axes[2]
        assert self._setpoint is not None
        d_set = self.probe.distance_at(self._setpoint - self.charging_offset(t))
        base = z.true_position(t) - z.extension(t)
        out: FloatArray = self.params.z_top - np.asarray(height) - d_set - base
        return out

    def _settle_loop(self, t: float) -> None:
        x, y = self.sample_xy(t)
        h = self.surface_height(np.array([x]), np.array([y]), t)
        ext = float(self._required_extension(h, t)[0])
        z = self.robot_device.axes[2]
        rng = z.params.fine_range
        self._saturated = not 0.0 <= ext <= rng
        z.drive_extension(float(np.clip(ext, 0.0, rng)), t)
        if self.distance(t) < 0:
            self.crashed = True

    # -- spoiled scans ----------------------------------------------------------------------

    def spoil_next_scan(self, kind: str, *, lines: int) -> None:
        """Spoil the next scan of ``lines`` lines as fault ``kind`` does in real life, from
        its strike line on (:func:`hardware.sim.faults.strike_line`): the tip turns blunt
        (``tip_change``), the loop parachutes after steps down (``parachute``), a block of
        lines is lost (``lost_lines``), or the sample jumps in Z (``z_jump``, for good)."""
        self._spoiling = ArmedFault.arm(kind, lines)

    @property
    def spoiling(self) -> str | None:
        """The fault armed for the scan under way or the next, if any."""
        return None if self._spoiling is None else self._spoiling.kind

    def _spoiled_line(self) -> tuple[str | None, bool]:
        """The fault acting on the line about to be recorded (None: none), and whether its
        data are lost; counts the line."""
        armed = self._spoiling
        if armed is None:
            return None, False
        kind, lost, jump = armed.next_line()
        if armed.over:
            self._spoiling = None
        if jump:
            self.sample_z += Z_JUMP
        return kind, lost

    # -- LineRecorder -----------------------------------------------------------------------

    def record_line(self, samples: int, duration: float) -> tuple[FloatArray, float]:
        """Record the tip height ``samples`` times over the next ``duration`` seconds.

        The axes move as the control software commanded them just before (the X ramp of a
        raster line); the force loop, engaged, tracks the surface with its finite bandwidth:
        the loop had followed the surface during the fly-back, so it starts settled. Returns
        the heights (metres) and the start time.
        """
        if self._setpoint is None:
            raise ProcedureError("engage the force loop before recording")
        if samples < 1 or not duration > 0:
            raise ValueError("need at least one sample and a positive duration")
        kind, lost = self._spoiled_line()
        params, slew = self.params, self._slew_rate
        if kind == "tip_change":
            self.params = replace(params, tip_radius=BLUNT_TIP)
        elif kind == "parachute":
            self._slew_rate = PARACHUTE_RATE
        try:
            line, t0 = self._record(samples, duration)
        finally:
            self.params, self._slew_rate = params, slew
        if lost:
            line = np.full(samples, np.nan)
        return line, t0

    def _record(self, samples: int, duration: float) -> tuple[FloatArray, float]:
        """:meth:`record_line` itself (a spoiling fault set up around it)."""
        setpoint = self._setpoint
        if setpoint is None:
            raise ProcedureError("engage the force loop before recording")
        t0 = self.clock.now()
        self._settle_loop(t0)
        z = self.robot_device.axes[2]
        # the true tip path over the line, from the channels at a few knots (the ramp is
        # smooth: linear in level, bent slightly by hysteresis and creep)
        knots = np.linspace(t0, t0 + duration, 9)
        path = np.array([self.sample_xy(t) for t in knots])
        length = float(np.hypot(*(path[-1] - path[0])))
        # the loop's knots a few nanometres apart (at least four a pixel): what it follows
        # depends on speed and slope, not on the pixels
        sub = max(self.params.substeps, math.ceil(length / samples / KNOT_SPACING))
        dt = duration / (samples * sub)
        loop = Loop(
            bandwidth=self.params.loop_bandwidth,
            knot_time=dt,
            substeps=sub,
            zrange=z.params.fine_range,
            branch_end=self.probe.attraction_minimum(),
            crash_depth=self.probe.crash_distance(),
            slew_rate=self._slew_rate,
        )
        ts = t0 + dt * (np.arange(samples * sub) + 0.5)
        xs = np.interp(ts, knots, path[:, 0])
        ys = np.interp(ts, knots, path[:, 1])
        # a pixel is the mean over its time slice (the controller averages its samples)
        self.line_positions.append(
            np.column_stack([xs.reshape(samples, sub).mean(1), ys.reshape(samples, sub).mean(1)])
        )
        # the sample drifts in Z during the line too (a slow line meets more of it)
        surf = self.surface_height(xs, ys, t0) + self._drift_v[2] * (ts - t0)
        ext = z.extension(t0)
        tip0 = self.params.z_top - (z.true_position(t0) - ext)
        d_set = self.probe.distance_at(setpoint - self.charging_offset(t0))
        if self._jump:  # a step in no time: the tip meets it with the extension it had
            jump, self._jump = self._jump, 0.0
            self.sample_z += jump
            if jump > d_set - loop.crash_depth:
                self.crashed = True
                raise CrashError(
                    f"the tip crashed into the surface: the sample jumped {jump * 1e9:.3g} nm "
                    "up under it mid-line, faster than any force loop follows"
                )
            surf[len(surf) // 2 :] += jump
        try:
            followed = follow_line(surf, tip0, ext, d_set, loop)
        except CrashError:
            self.crashed = True
            raise
        self._tracking = followed.tracking
        self._saturated = self._saturated or followed.saturated
        ext = followed.extension
        self.clock.advance_to(t0 + duration)
        z.drive_extension(ext, self.clock.now())
        return followed.heights + self.rng.normal(0.0, self.params.z_noise, samples), t0
