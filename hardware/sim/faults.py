"""The faults that spoil a patch in real life, as they spoil its recorded heights.

A tip that changes mid-patch (picks up a particle, or breaks: from then on the image is the
surface dilated by a blunter tip), a loop that parachutes (after a step down it loses the
surface and falls back at its slew rate), a block of lines the controller loses, and a sudden
Z jump (the sample or the scanner slips). Each acts from a line on, as in time.

:func:`spoil` applies one to a recorded image (rows are scan lines, in time order); the
simulated instrument spoils its own scans line by line with the same physics
(:meth:`hardware.sim.instrument.SimulatedAFM.spoil_next_scan`: a blunter tip, a slower loop,
lines lost, the sample lifted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]

Spoiling = Literal["tip_change", "parachute", "lost_lines", "z_jump"]
#: The spoiling faults, by name.
SPOILING: tuple[str, ...] = get_args(Spoiling)

#: Radius of the blunt tip after a tip change, metres (a sharp tip is ~10 nm).
BLUNT_TIP = 60e-9
#: How fast a parachuting tip falls back to the surface, metres per pixel along the line.
PARACHUTE_RATE = 1.5e-9
#: Share of the lines a lost block holds.
LOST_SHARE = 0.15
#: Height of a sudden Z jump, metres.
Z_JUMP = 25e-9
#: Where in the patch the fault strikes, as a fraction of its lines.
STRIKE = 0.45


def strike_line(lines: int) -> int:
    """The line the fault strikes on, of ``lines``."""
    return min(lines - 1, max(1, round(STRIKE * lines)))


@dataclass
class ArmedFault:
    """A fault armed for one scan of ``lines`` lines, as the simulated instrument spoils it
    line by line: its ``kind``, the line it strikes on and the lines recorded so far."""

    kind: str
    lines: int
    strike: int
    recorded: int = 0

    @classmethod
    def arm(cls, kind: str, lines: int) -> ArmedFault:
        """Fault ``kind`` (one of :data:`SPOILING`) for the next scan of ``lines`` lines,
        striking on :func:`strike_line`."""
        if kind not in SPOILING:
            raise ValueError(f"unknown fault {kind!r}; expected one of {', '.join(SPOILING)}")
        if lines < 2:
            raise ValueError(f"a spoiled scan needs at least 2 lines, got {lines}")
        return cls(kind, lines, strike_line(lines))

    @property
    def over(self) -> bool:
        """Whether every line of its scan has been recorded."""
        return self.recorded >= self.lines

    def next_line(self) -> tuple[str | None, bool, bool]:
        """The fault acting on the line about to be recorded (None: it has not struck yet),
        whether that line's data are lost, and whether the sample jumps in Z at it; counts
        the line."""
        k = self.recorded
        self.recorded += 1
        if k < self.strike:
            return None, False, False
        lost = self.kind == "lost_lines" and k < self.strike + max(
            1, round(LOST_SHARE * self.lines)
        )
        return self.kind, lost, self.kind == "z_jump" and k == self.strike


def spoil(heights: FloatArray, kind: str, *, pixel_size: tuple[float, float]) -> FloatArray:
    """``heights`` (ny, nx; rows are scan lines in time order, metres) as fault ``kind`` leaves
    them, from line :func:`strike_line` on.

    Parameters
    ----------
    heights : (ny, nx) array
    kind : {"tip_change", "parachute", "lost_lines", "z_jump"}
    pixel_size : (dx, dy), keyword-only
        Pixel pitch, metres (the tip's footprint and the fall-back rate are physical).
    """
    if kind not in SPOILING:
        raise ValueError(f"unknown fault {kind!r}; expected one of {', '.join(SPOILING)}")
    h = np.array(heights, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {h.shape}")
    k = strike_line(h.shape[0])
    if kind == "z_jump":
        h[k:] += Z_JUMP
    elif kind == "lost_lines":
        h[k : k + max(1, round(LOST_SHARE * h.shape[0]))] = np.nan
    elif kind == "tip_change":
        h[k:] = dilate(h, BLUNT_TIP, pixel_size)[k:]
    else:
        h[k:] = parachute(h[k:], PARACHUTE_RATE)
    return h


def dilate(heights: FloatArray, radius: float, pixel_size: tuple[float, float]) -> FloatArray:
    """The image a spherical tip of ``radius`` (metres) records: every point is the highest
    the sphere's apex reaches over it (grey dilation by the sphere's cap)."""
    dx, dy = pixel_size
    ry, rx = math.ceil(radius / dy), math.ceil(radius / dx)
    yy, xx = np.mgrid[-ry : ry + 1, -rx : rx + 1]
    d2 = (xx * dx) ** 2 + (yy * dy) ** 2
    inside = d2 <= radius**2
    cap = np.where(inside, -(radius - np.sqrt(np.maximum(radius**2 - d2, 0.0))), 0.0)
    filled = np.where(np.isfinite(heights), heights, np.nanmin(heights))
    out: FloatArray = ndimage.grey_dilation(filled, footprint=inside, structure=cap, mode="nearest")
    return np.where(np.isfinite(heights), out, np.nan)


def parachute(lines: FloatArray, rate: float) -> FloatArray:
    """Scan ``lines`` (rows, along the fast axis) of a loop that, once it loses the surface
    after a step down, falls back at most ``rate`` metres per pixel."""
    out = np.array(lines, dtype=np.float64)
    for j in range(1, out.shape[1]):
        out[:, j] = np.maximum(out[:, j], out[:, j - 1] - rate)
    return out
