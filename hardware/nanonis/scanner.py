"""A patch scanned by the Nanonis scan generator: frame, buffer, speed, start, wait, grab.

The frame is centred in the scan range (the sample stage brings the patch there), so its
pixel ``(0, 0)`` lies at fine extension ``(range - size) / 2 + pixel / 2`` as in the fine-mode
raster. The scan runs upwards, so the first line recorded is the frame's bottom row and the
grabbed rows run along +y. While it runs, the scanner waits one line period at a time and
between waits checks what a supervisor would: the caller's stop request, the PLL's lock, the
Z controller still on, and the frame's overall time-out. Whatever goes wrong, the frame is
stopped before the error leaves.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from hardware.errors import CrashError, Interrupted, ProcedureError
from hardware.nanonis.client import SCAN_START, SCAN_STOP, NanonisClient
from hardware.nanonis.roles import NanonisProbe, ZPiezo
from hardware.protocols import ScanLines


class NanonisScanner:
    """:class:`~hardware.protocols.PatchScanner` on a Nanonis scan module.

    Parameters
    ----------
    client : NanonisClient
    z : ZPiezo
        The Z limits (a pixel at either limit means the loop saturated).
    probe : NanonisProbe
        Checked for lock while the frame runs.
    z_channel : int
        The signal slot of Z in the scan buffer (checked by name when grabbed).
    angle : float
        Frame angle, degrees clockwise: the rotation of the scan axes against the sample
        stage's, measured once per set-up (0 when they are aligned).
    backward_ratio : float
        Backward speed over forward speed (the fly-back line).
    frame_margin : float
        Seconds beyond the frame's own duration before it counts as hung.
    """

    def __init__(
        self,
        client: NanonisClient,
        z: ZPiezo,
        probe: NanonisProbe,
        *,
        z_channel: int = 14,
        angle: float = 0.0,
        backward_ratio: float = 1.0,
        frame_margin: float = 10.0,
    ) -> None:
        if not backward_ratio > 0:
            raise ValueError(f"backward_ratio must be positive, got {backward_ratio}")
        self.client, self.z, self.probe = client, z, probe
        self.z_channel, self.angle = z_channel, angle
        self.backward_ratio, self.frame_margin = backward_ratio, frame_margin
        rx, ry, _ = client.piezo_range()
        self._range = (rx, ry)
        #: what :meth:`prepare` programmed for the next scan (None: nothing yet)
        self._programmed: tuple[tuple[float, float], tuple[int, int]] | None = None

    @property
    def fine_range(self) -> tuple[float, float]:
        return self._range

    def prepare(self, *, size: tuple[float, float], pixels: tuple[int, int]) -> None:
        """Program the frame and buffer; take the tip to the frame's first line (so the long
        move's creep relaxes while the tip lands)."""
        self._program(size, pixels)
        self._programmed = (size, pixels)
        w, h = size
        self.client.set_tip_speed(10 * max(self._range))
        self.client.move_tip(-w / 2, -h / 2)

    def _program(self, size: tuple[float, float], pixels: tuple[int, int]) -> None:
        nx, ny = pixels
        w, h = size
        if not (0 < w <= self._range[0] and 0 < h <= self._range[1]):
            raise ValueError(
                f"a patch must fit the scan range {self._range[0]:g} x {self._range[1]:g} m, "
                f"got {w:g} x {h:g} m"
            )
        self.client.set_frame((0.0, 0.0), size, self.angle)
        self.client.set_buffer([self.z_channel], nx, ny)
        _, got_nx, got_ny = self.client.buffer()
        if (got_nx, got_ny) != (nx, ny):
            raise ProcedureError(
                f"the Nanonis scan buffer took {got_nx} x {got_ny} pixels for {nx} x {ny}: "
                "pixels per line must be a multiple of 16 there (plan 16, 32, 48, 64, ...)"
            )

    def scan(
        self,
        *,
        size: tuple[float, float],
        pixels: tuple[int, int],
        line_rate: float,
        stop: Callable[[], bool] | None = None,
    ) -> ScanLines:
        if not line_rate > 0:
            raise ValueError(f"line rate must be positive, got {line_rate}")
        nx, ny = pixels
        if self._programmed != (size, pixels):
            self._program(size, pixels)
        self._programmed = None  # the next scan programs its own frame unless prepared
        forward = 1.0 / line_rate
        backward = forward / self.backward_ratio
        self.client.set_speed(forward, backward, size[0])
        period = forward + backward
        started = time.time()
        self.client.scan_action(SCAN_START, up=True)
        try:
            self._wait(ny * period, period, stop)
            name, data, up = self.client.grab_frame(self.z_channel, forward=True)
        except BaseException:
            self.stop()
            raise
        heights = self._check(name, np.asarray(data, dtype=np.float64), up, (ny, nx))
        dx, dy = size[0] / nx, size[1] / ny
        origin = ((self._range[0] - size[0] + dx) / 2, (self._range[1] - size[1] + dy) / 2)
        return ScanLines(
            heights=heights,
            line_times=started + period * np.arange(ny, dtype=np.float64),
            origin=origin,
            pixel_size=(dx, dy),
            saturated=self._saturated(heights),
        )

    def _wait(self, duration: float, period: float, stop: Callable[[], bool] | None) -> None:
        deadline = time.monotonic() + 1.5 * duration + self.frame_margin
        while not self.client.wait_end_of_scan(min(period, max(0.01, duration))):
            if stop is not None and stop():
                raise Interrupted("scan stopped on request")
            if not self.probe.locked():
                raise CrashError("the PLL lost lock during the scan: the tip may have crashed")
            if not self.client.z_controller_on():
                raise ProcedureError("the Z controller switched off during the scan")
            if time.monotonic() > deadline:
                raise ProcedureError(
                    f"the frame did not end within {1.5 * duration + self.frame_margin:.0f} s "
                    f"(its scan takes {duration:.0f} s): the scan generator may be stuck"
                )
        if not self.probe.locked():
            raise CrashError("the PLL lost lock during the scan: the tip may have crashed")

    def _check(self, name: str, data: np.ndarray, up: bool, shape: tuple[int, int]) -> np.ndarray:
        if not name.startswith("Z"):
            raise ProcedureError(
                f"scan channel {self.z_channel} is {name!r}, not Z: set z_channel to Z's slot"
            )
        if data.shape != shape:
            raise ProcedureError(f"the frame came back {data.shape}, expected {shape} (ny, nx)")
        heights = data if up else data[::-1]
        return np.ascontiguousarray(heights, dtype=np.float64)

    def _saturated(self, heights: np.ndarray) -> np.ndarray:
        """(ny,) whether a line has a pixel at a Z limit (the loop saturated there)."""
        margin = 2e-3 * self.z.range
        with np.errstate(invalid="ignore"):
            at = (heights >= self.z.high - margin) | (heights <= self.z.low + margin)
        return np.asarray(at.any(axis=1))

    def stop(self) -> None:
        self.client.scan_action(SCAN_STOP)
