"""What a scan may ask of the instrument: how fast the force loop follows the sample, and how
long Z's fine range lasts against drift. Pure: numbers in, limits out.

The Z loop is a first-order regulator of bandwidth ``f``: crossing a slope ``s`` at speed
``v`` it lags ``s v / (2π f)`` behind the surface, and the tip touches it once that lag passes
the set-point's clearance (the distance from the set-point to where the PLL loses the
resonance). So the fastest safe tip speed is ``2π f margin / s``, ``s`` the steepest rising
slope the tip meets. A landing centres Z's fine range; within a patch the sample's relief and
the Z drift over the patch's time both spend that half range, so a patch may last
``(range / 2 - relief) / drift`` at most (never less than an eighth of the range's worth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The line rates (lines per second) a scanner of this kind runs at.
LINE_RATES = (0.1, 10.0)


@dataclass(frozen=True)
class ScanEnvelope:
    """The limits of a scan on one instrument and sample (SI units).

    loop_bandwidth : Hz, of the Z (force) loop.
    tracking_margin : metres the loop may lag behind a rising surface before the tip touches.
    sample_slope : the steepest rising slope the tip meets along a line (an estimate).
    sample_relief : metres of height within one patch (an estimate).
    z_drift : metres per second, the largest Z drift the instrument is specified for.
    z_range : metres, Z's fine range.
    line_rates : the scanner's range of line rates, lines per second.
    """

    loop_bandwidth: float = 1000.0
    tracking_margin: float = 2.5e-9
    sample_slope: float = 3.0
    sample_relief: float = 0.5e-6
    z_drift: float = 1e-9
    z_range: float = 1.6e-6
    line_rates: tuple[float, float] = LINE_RATES

    def __post_init__(self) -> None:
        values = (
            self.loop_bandwidth,
            self.tracking_margin,
            self.sample_slope,
            self.z_drift,
            self.z_range,
            *self.line_rates,
        )
        if not all(math.isfinite(v) and v > 0 for v in values) or self.sample_relief < 0:
            raise ValueError(f"a scan envelope needs positive finite numbers, got {self}")

    @property
    def max_speed(self) -> float:
        """The fastest tip speed (m/s) at which the loop follows the steepest slope."""
        return 2 * math.pi * self.loop_bandwidth * self.tracking_margin / self.sample_slope

    @property
    def z_budget(self) -> float:
        """Metres of Z's fine range a patch's drift may spend."""
        return max(self.z_range / 2 - self.sample_relief, self.z_range / 8)

    @property
    def max_patch_time(self) -> float:
        """The longest a patch's scan may last (s) before drift may take Z out of range."""
        return self.z_budget / self.z_drift

    def problems(self, *, width: float, lines: int, line_rate: float) -> list[str]:
        """What is wrong with scanning ``lines`` lines of ``width`` metres at ``line_rate``
        lines per second (empty: nothing); each names the limit and what to change."""
        lo, hi = self.line_rates
        if not lo <= line_rate <= hi:
            return [f"{line_rate:g} lines/s is outside the scanner's {lo:g}-{hi:g} lines/s"]
        out = []
        speed = width * line_rate
        if speed > self.max_speed:
            out.append(
                f"the tip would cross {width * 1e6:.3g} µm at {speed * 1e6:.3g} µm/s, but on "
                f"slopes up to {self.sample_slope:.3g} the force loop ({self.loop_bandwidth:g} "
                f"Hz) follows at most {self.max_speed * 1e6:.3g} µm/s: use at most "
                f"{self.max_speed / width:.3g} lines/s, or narrower patches"
            )
        duration = lines / line_rate
        if duration > self.max_patch_time:
            out.append(
                f"a patch of {lines} lines at {line_rate:g} lines/s takes "
                f"{duration / 60:.3g} min, over which Z drift (up to "
                f"{self.z_drift * 60e9:.3g} nm/min) could take Z out of its range: use at least "
                f"{lines / self.max_patch_time:.3g} lines/s, or fewer lines"
            )
        return out
