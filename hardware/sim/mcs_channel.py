"""One simulated MCS channel: a stick-slip positioner with a fine mode and a position sensor.

The model, in SI units and simulated seconds:

* **Stepping** (open loop): each step moves the slider by a size proportional to the amplitude,
  larger forward than backward (stick-slip is asymmetric), scattering ±10 % from step to step;
  now and then a step is lost. Steps take ``1 / frequency`` each. The slider stops at the
  mechanical end stops.
* **Fine mode** (scan): the piezo extends over ``fine_range`` for voltage levels 0..4095, with a
  little hysteresis (the up and down branches differ) and creep: after a fine move the
  extension keeps drifting a fraction of that move, relaxing exponentially.
* **Closed loop** (``:MPA``/``:MPR``): the controller steps and then fine-tunes until the sensor
  reads the target; it needs a sensor and respects the soft range limit.
* **Slider creep**: after stepping, the slider keeps moving a fraction of the stepped distance,
  relaxing exponentially (on a Z axis this is the drift that makes a mosaic's Z staircase).
* **Sensor**: reads slider + extension with white noise, a scale error and the periodic error
  of its encoder, so a closed-loop move lands where the sensor, not the truth, says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hardware.smaract_mcs import MAX_LEVEL, AxisStatus


@dataclass(frozen=True)
class ChannelParams:
    """Physical parameters of a channel (metres, seconds)."""

    travel: tuple[float, float] = (-6e-3, 6e-3)
    step_size: float = 100e-9
    backward_ratio: float = 0.92
    step_scatter: float = 0.10
    lost_step_probability: float = 0.002
    fine_range: float = 1.6e-6
    hysteresis: float = 0.015
    creep_fraction: float = 0.01
    creep_time: float = 20.0
    step_creep_fraction: float = 0.02
    step_creep_time: float = 60.0
    sensor_noise: float = 1e-9
    sensor_scale_error: float = 0.0  # relative error of the sensor's scale
    sensor_periodic_error: float = 0.0  # amplitude (m) of the encoder's periodic error
    sensor_period: float = 4e-6  # its period, m
    has_sensor: bool = True
    closed_loop_speed: float = 1e-3


@dataclass
class _Motion:
    status: AxisStatus
    t0: float
    t1: float
    slider0: float
    slider1: float
    level0: float
    level1: float
    hold_until: float = 0.0


@dataclass
class MCSChannel:
    """State and physics of one channel; every method takes the simulated time ``t``."""

    params: ChannelParams = field(default_factory=ChannelParams)
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    slider: float = 0.0
    # fractional: an analogue loop drives the piezo between the controller's whole levels
    level: float = 0.0
    limit: tuple[float, float] | None = None
    _motion: _Motion | None = None
    # creep of all past fine moves (one time constant, so they sum exactly):
    # c(t) = c_inf - (c_inf - c0) exp(-(t - t0) / tau)
    _creep0: float = 0.0
    _creep_inf: float = 0.0
    _creep_t0: float = 0.0
    _slide0: float = 0.0
    _slide_inf: float = 0.0
    _slide_t0: float = 0.0
    _rising: bool = True

    # -- what the controller can read -----------------------------------------------------------

    def status(self, t: float) -> AxisStatus:
        m = self._motion
        if m is None:
            return AxisStatus.STOPPED
        if t < m.t1:
            return m.status
        if t < m.hold_until:
            return AxisStatus.HOLDING
        self._settle(t)
        return AxisStatus.STOPPED

    def busy_until(self, t: float) -> float:
        """Simulated time at which the current motion (and hold) ends; ``t`` if idle."""
        m = self._motion
        return max(t, m.t1, m.hold_until) if m is not None else t

    def extension(self, t: float) -> float:
        """Fine-mode extension now, metres: level, hysteresis and creep."""
        return self._ext_without_creep(self.level_at(t)) + self.creep(t)

    def creep(self, t: float) -> float:
        decay = np.exp(-max(t - self._creep_t0, 0.0) / self.params.creep_time)
        return float(self._creep_inf - (self._creep_inf - self._creep0) * decay)

    def true_position(self, t: float) -> float:
        """Where the positioner really is, metres (slider, its creep, and extension)."""
        return self._slider_at(t) + self.slider_creep(t) + self.extension(t)

    def slider_creep(self, t: float) -> float:
        decay = np.exp(-max(t - self._slide_t0, 0.0) / self.params.step_creep_time)
        return float(self._slide_inf - (self._slide_inf - self._slide0) * decay)

    def drive_extension(self, extension: float, t: float) -> float:
        """Set the fine level whose extension (hysteresis and creep included) is closest to
        ``extension`` metres, as a feedback loop on the piezo would; returns the extension."""
        self._settle(t)
        target = extension - self.creep(t)
        self._rising = target >= self._ext_without_creep(self.level)
        level = self.level
        for _ in range(6):  # the hysteresis bow is a few per cent: fixed point converges fast
            error = target - self._ext_without_creep(level)
            level = float(np.clip(level + error / self.params.fine_range * MAX_LEVEL, 0, MAX_LEVEL))
        self.level = level
        return self.extension(t)

    def drive_level(self, level: int, t: float) -> None:
        """Set the fine level directly, as an analogue force loop drives the Z piezo."""
        self._settle(t)
        level = int(np.clip(level, 0, MAX_LEVEL))
        self._rising = level >= self.level
        self.level = level

    def sensor(self, t: float) -> float:
        return self._reading(self.true_position(t)) + float(
            self.rng.normal(0.0, self.params.sensor_noise)
        )

    def _reading(self, x: float) -> float:
        """What the (noise-free) sensor reports at true position ``x``."""
        p = self.params
        periodic = p.sensor_periodic_error * math.sin(2 * math.pi * x / p.sensor_period)
        return x * (1.0 + p.sensor_scale_error) + periodic

    def _true_for_reading(self, reading: float) -> float:
        """The true position where the sensor reads ``reading`` (fixed point)."""
        x = reading
        for _ in range(20):
            x += (reading - self._reading(x)) / (1.0 + self.params.sensor_scale_error)
        return x

    # -- commands ------------------------------------------------------------------------------

    def step(self, steps: int, amplitude: int, frequency: int, t: float) -> None:
        self._settle(t)
        if steps == 0 or amplitude == 0:
            return
        n = abs(steps)
        size = self.params.step_size * amplitude / MAX_LEVEL
        if steps < 0:
            size *= -self.params.backward_ratio
        sizes = size * (1 + self.rng.uniform(-1, 1, n) * self.params.step_scatter)
        sizes[self.rng.random(n) < self.params.lost_step_probability] = 0.0
        lo, hi = self.params.travel
        target = float(np.clip(self.slider + sizes.sum(), lo, hi))
        duration = n / frequency
        if target in (lo, hi):  # ran into an end stop: the steps after it go nowhere
            done = np.abs(target - self.slider) / max(abs(size), 1e-30)
            duration = min(duration, done / frequency)
        self._motion = _Motion(
            AxisStatus.STEPPING, t, t + duration, self.slider, target, self.level, self.level
        )

    def scan(self, level: int, speed: int, t: float) -> None:
        self._settle(t)
        level = int(np.clip(level, 0, MAX_LEVEL))
        if level == self.level:
            return
        self._rising = level > self.level
        duration = abs(level - self.level) / speed
        self._motion = _Motion(
            AxisStatus.SCANNING, t, t + duration, self.slider, self.slider, self.level, level
        )

    def move_to(self, target: float, hold_ms: int, t: float) -> None:
        """Closed loop: slider and fine mode end where the sensor reads ``target``."""
        self._settle(t)
        target = self._true_for_reading(target)
        duration = abs(target - self.true_position(t)) / self.params.closed_loop_speed + 0.01
        # the controller keeps the fine mode mid-range and places the slider for the rest,
        # reading the sensor, so hysteresis and the creep at arrival are compensated
        level = MAX_LEVEL // 2
        self._rising = level > self.level
        t1 = t + duration
        slider = target - self._ext_without_creep(level) - self.creep(t1) - self.slider_creep(t1)
        self._motion = _Motion(
            AxisStatus.TARGETING,
            t,
            t1,
            self.slider,
            slider,
            self.level,
            level,
            hold_until=t1 + hold_ms / 1000.0,
        )

    def stop(self, t: float) -> None:
        m = self._motion
        if m is not None and t < m.t1:
            self.slider = self._slider_at(t)
            self.level = self.level_at(t)
            self._motion = None

    # -- internals -----------------------------------------------------------------------------

    def _ext_without_creep(self, level: float) -> float:
        frac = level / MAX_LEVEL
        bow = self.params.hysteresis * 4 * frac * (1 - frac)
        frac += -bow / 2 if self._rising else bow / 2
        return frac * self.params.fine_range

    def _progress(self, t: float) -> float:
        m = self._motion
        if m is None or m.t1 <= m.t0:
            return 1.0
        return float(np.clip((t - m.t0) / (m.t1 - m.t0), 0.0, 1.0))

    def _slider_at(self, t: float) -> float:
        m = self._motion
        if m is None:
            return self.slider
        return m.slider0 + (m.slider1 - m.slider0) * self._progress(t)

    def level_at(self, t: float) -> float:
        """Fine-mode voltage level now, 0..4095 (fractional while an analogue loop drives it)."""
        m = self._motion
        if m is None:
            return self.level
        return m.level0 + (m.level1 - m.level0) * self._progress(t)

    def _settle(self, t: float) -> None:
        """Finish a motion that has ended (starting creep for its fine part), or stop a
        running one: a new command overrides it."""
        m = self._motion
        if m is None:
            return
        if t < m.t1:
            self.stop(t)
            return
        # a hold still running ends here too: the new command takes over
        stepped = m.slider1 - m.slider0
        if m.status is AxisStatus.STEPPING and stepped:
            self._slide0 = self.slider_creep(m.t1)
            self._slide_inf += self.params.step_creep_fraction * stepped
            self._slide_t0 = m.t1
        moved = (m.level1 - m.level0) / MAX_LEVEL * self.params.fine_range
        if moved:
            self._creep0 = self.creep(m.t1)
            self._creep_inf += self.params.creep_fraction * moved
            self._creep_t0 = m.t1
        self.slider, self.level = m.slider1, m.level1
        self._motion = None
