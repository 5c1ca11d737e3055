"""The simulated SEM: secondary-electron images of the sample with a known calibration.

Contrast, as an Everhart-Thornley detector sees a surface: the secondary-electron yield grows
with the local tilt (about ``1 / cos θ``), so edges and slopes are bright; the side-mounted
detector adds shading (faces turned towards it are brighter); convex edges brighten further
(electrons escape through the side wall too); shot noise on top. Pixel
``(col, row)`` of an image lies at stage (sample) position ``origin + (col, -row) * pixel``:
row 0 is the top line, as an SEM shows it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from hardware.protocols import SEMFrame, SEMImage
from hardware.sim.surfaces import Surface

FloatArray = NDArray[np.float64]

#: The charging drift of the field's centre between two frames, metres (a random walk).
CHARGING_STEP = 3e-9
#: Edge brightening: secondary electrons escape from within ``SE_ESCAPE`` of a convex edge
#: (metres); an edge curving by ``SE_DEPTH`` over that range brightens by about
#: ``EDGE_GAIN`` (the yield of a flat surface is 1).
SE_ESCAPE = 10e-9
SE_DEPTH = 5e-9
EDGE_GAIN = 0.5


class SimulatedSEM:
    """An SEM looking at ``surface``.

    Parameters
    ----------
    surface : Surface
    noise : float
        Relative shot noise of a pixel.
    detector : (dx, dy)
        Horizontal direction of the secondary-electron detector (unit vector).
    seed : int
    geometry : SEMGeometry
        How its scan sits over the sample stage (:meth:`acquire`; the truth a calibration
        must find).
    stage : callable, optional
        The sample stage's true position (x, y metres), whose moves the SEM sees the sample
        make; default fixed at the origin.
    sensor_scale : float
        How the stage's position sensors scale a true length (1 + their scale error). The
        geometry is given in the stage's frame as its sensors read it (the frame every
        position is commanded and recorded in, so the map a calibration can find): the
        SEM's true scale over the sample is ``geometry.scale / sensor_scale``.
    """

    def __init__(
        self,
        surface: Surface,
        *,
        noise: float = 0.05,
        detector: tuple[float, float] = (0.7071, 0.7071),
        seed: int = 0,
        geometry: SEMGeometry | None = None,
        stage: Callable[[], tuple[float, float]] | None = None,
        sensor_scale: float = 1.0,
    ) -> None:
        if not 0.9 < sensor_scale < 1.1:
            raise ValueError(f"sensor_scale must be within 10 % of 1, got {sensor_scale}")
        self.sensor_scale = sensor_scale
        self.surface = surface
        self.geometry = geometry or SEMGeometry()
        self.stage = stage or (lambda: (0.0, 0.0))
        self.frames = 0
        self.field = 50e-6
        self.rotation = 0.0
        #: the SEM's own stage (x, y, z metres, rotation, tilt degrees): it does not move here
        self.sem_stage = (0.0, 0.0, 0.01, 0.0, 0.0)
        self.noise = noise
        self.detector = np.asarray(detector, dtype=np.float64)
        self.rng = np.random.default_rng(seed)

    def acquire(
        self,
        *,
        field: float,
        pixels: int,
        dwell: float = 1e-6,
        detector: str = "SE",
        scan_rotation: float | None = None,
    ) -> SEMFrame:
        """A frame through its true :attr:`geometry`, the sample where the stage put it, the
        field's centre crept by charging since the last frame (a random walk of
        :data:`CHARGING_STEP`), the noise falling with the square root of ``dwell``."""
        if not (field > 0 and 8 <= pixels <= 8192 and 1e-8 <= dwell <= 1e-3):
            raise ValueError(f"cannot scan {pixels} px over {field} m at {dwell} s a pixel")
        if detector.upper() not in ("SE", "BSE", "INBEAM"):
            raise ValueError(f"no detector {detector!r}: SE, BSE or InBeam")
        self.frames += 1
        self.field = field
        scan_rotation = self.rotation if scan_rotation is None else scan_rotation
        step = self.rng.normal(0.0, CHARGING_STEP, 2)
        ox, oy = self.geometry.offset
        self.geometry = replace(self.geometry, offset=(ox + step[0], oy + step[1]))
        sx, sy = self.stage()  # a lab point shows the sample point the stage put there
        k = self.sensor_scale  # the geometry in the stage's readings, rendered in true metres
        g = self.geometry
        seen = replace(g, scale=g.scale / k, offset=(g.offset[0] / k - sx, g.offset[1] / k - sy))
        image = render_frame(
            self, seen, field=field, pixels=pixels, scan_rotation=scan_rotation, dwell=dwell
        )
        return SEMFrame(
            image, field / pixels, scan_rotation, self.sem_stage[:3], field, dwell, detector
        )

    def view_field(self) -> float:
        return self.field

    def scan_rotation(self) -> float:
        return self.rotation

    def stage_position(self) -> tuple[float, float, float, float, float]:
        return self.sem_stage

    def true_map(self) -> dict[str, object]:
        """The SEM's true geometry over the stage, as ``GET /api/instrument/sim/sem`` gives
        it: rotation (degrees), scale and the field centre's lab position (metres), in the
        stage's frame as its sensors read it."""
        g = self.geometry
        return {"rotation_deg": g.rotation, "scale": g.scale, "offset": list(g.offset)}

    def grab(self, *, centre: tuple[float, float], field: float, pixels: int) -> SEMImage:
        """An image ``field`` metres wide, ``pixels`` square, centred on ``centre`` (stage),
        as a perfectly calibrated SEM would take and place it (no rotation, no scale error,
        no charging): the sample as the tests' ground truth sees it."""
        if not field > 0:
            raise ValueError(f"field must be positive, got {field}")
        if not 8 <= pixels <= 4096:
            raise ValueError(f"pixels must be in 8..4096, got {pixels}")
        perfect = SEMGeometry(rotation=0.0, scale=1.0, offset=centre)
        signal = render_frame(self, perfect, field=field, pixels=pixels)
        pitch = field / pixels
        # row 0 the top line, as an SEM shows it: rows go down the stage's y
        origin = (centre[0] - field / 2 + pitch / 2, centre[1] + field / 2 - pitch / 2)
        matrix = ((pitch, 0.0), (0.0, -pitch))
        return SEMImage(pixels=signal, origin=origin, pixel_size=(pitch, pitch), matrix=matrix)

    def signal(self, x: FloatArray, y: FloatArray, noise: float) -> FloatArray:
        """The secondary-electron signal at stage points ``x``, ``y`` (a 2-D grid of them,
        metres, of any orientation): tilt yield, detector shading and relative shot
        ``noise``."""
        h = self.surface.height(x, y)
        h = np.where(np.isfinite(h), h, np.nanmin(h) if np.isfinite(h).any() else 0.0)
        # the slopes along the stage's axes, from the grid's own neighbours (chain rule)
        h_r, h_c = np.gradient(h)
        x_r, x_c = np.gradient(x)
        y_r, y_c = np.gradient(y)
        det = x_c * y_r - x_r * y_c
        gx = (h_c * y_r - h_r * y_c) / det
        gy = (x_c * h_r - x_r * h_c) / det
        cos_tilt = 1.0 / np.sqrt(1.0 + gx**2 + gy**2)
        yield_ = 1.0 / cos_tilt  # tilt contrast: edges bright
        facing = (gx * self.detector[0] + gy * self.detector[1]) * cos_tilt
        out: FloatArray = yield_ * (1.0 - 0.3 * facing)  # faces sloping towards the detector
        # edge brightening: at a convex edge secondary electrons escape through the side
        # wall as well as the top, within their escape range of it
        spacing2 = np.abs(det)
        laplacian = (np.gradient(h_r, axis=0) + np.gradient(h_c, axis=1)) / spacing2
        out += EDGE_GAIN * np.tanh(np.maximum(-laplacian, 0.0) * SE_ESCAPE**2 / SE_DEPTH)
        out *= 1.0 + self.rng.normal(0.0, noise, out.shape)
        return out


@dataclass(frozen=True)
class SEMGeometry:
    """How an SEM sits over the sample stage, the truth a calibration must find: its scan
    axes are rotated by ``rotation`` degrees (counter-clockwise) and scaled by ``scale``
    against the stage's, and the centre of its field of view lies at ``offset`` (stage,
    metres)."""

    rotation: float = 3.0
    scale: float = 1.025
    offset: tuple[float, float] = (0.0, 0.0)

    def to_stage(self, u: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Stage positions of SEM-frame points ``(u, v)`` (metres from the field's centre,
        ``v`` up the screen)."""
        a = np.deg2rad(self.rotation)
        c, s = self.scale * np.cos(a), self.scale * np.sin(a)
        return self.offset[0] + c * u - s * v, self.offset[1] + s * u + c * v

    def frame_pixels(self, points: FloatArray, *, field: float, pixels: int) -> FloatArray:
        """Where a frame of ``field`` metres and ``pixels`` a side (no scan rotation, row 0
        the top line) shows stage points ``(..., 2)``: its (column, row) pixels, the truth a
        registration onto such a frame is scored against."""
        a = np.deg2rad(self.rotation)
        turn = self.scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        uv = (np.asarray(points) - np.asarray(self.offset)) @ np.linalg.inv(turn).T
        pitch, middle = field / pixels, (pixels - 1) / 2
        out: FloatArray = np.stack([uv[..., 0] / pitch + middle, middle - uv[..., 1] / pitch], -1)
        return out


def render_frame(
    sem: SimulatedSEM,
    geometry: SEMGeometry,
    *,
    field: float,
    pixels: int,
    scan_rotation: float = 0.0,
    dwell: float = 1e-6,
) -> FloatArray:
    """A frame as the SEM shows it (row 0 the top line) of ``field`` metres across, its scan
    turned by ``scan_rotation`` degrees, each pixel dwelt on ``dwell`` seconds: the shot noise
    falls as its square root (:attr:`SimulatedSEM.noise` at 1 µs)."""
    pitch = field / pixels
    k = (np.arange(pixels) - (pixels - 1) / 2) * pitch
    uu, vv = np.meshgrid(k, -k)  # row 0 at the top: v down the rows
    a = np.deg2rad(scan_rotation)
    u, v = np.cos(a) * uu - np.sin(a) * vv, np.sin(a) * uu + np.cos(a) * vv
    x, y = geometry.to_stage(u, v)
    noise = sem.noise * np.sqrt(1e-6 / dwell)
    return sem.signal(x, y, noise)
