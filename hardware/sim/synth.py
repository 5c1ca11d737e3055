"""Synthetic patch sets with known truth: a surface cut into drifting, noisy patches.

This is the fast path of the simulated instrument: no probe, no force loop, just the geometry of
the acquisition (stage errors, rotation, Z staircase, in-patch Z drift) and the noise. The true
transform of every patch is kept, so a merge can be scored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hardware.mosaic_plan import snake_grid
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import Surface

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SynthPatch:
    """One synthetic patch and its truth.

    The truth maps the nominal patch point ``p = (x, y, z_measured)`` to the true stage-frame
    point: ``q = R p + t - z_drift * (s - 1/2) e_z``, where ``s`` in [0, 1) is the pixel's scan
    time as a fraction of the patch (:func:`scan_fraction`).
    """

    id: str
    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    order: int
    row: int
    col: int
    rotation: FloatArray
    translation: FloatArray
    z_drift: float


def scan_fraction(shape: tuple[int, int]) -> FloatArray:
    """Scan time of every pixel as a fraction of the patch: raster, x fast, first row first."""
    ny, nx = shape
    out: FloatArray = (np.arange(ny * nx, dtype=np.float64) / (ny * nx)).reshape(ny, nx)
    return out


def true_points(patch: SynthPatch) -> FloatArray:
    """True stage-frame position of every measured point, ``(ny, nx, 3)``, metres."""
    ny, nx = patch.heights.shape
    x = patch.origin[0] + np.arange(nx) * patch.pixel_size[0]
    y = patch.origin[1] + np.arange(ny) * patch.pixel_size[1]
    xx, yy = np.meshgrid(x, y)
    p = np.stack([xx, yy, patch.heights], axis=-1)
    q = p @ patch.rotation.T + patch.translation
    q[..., 2] -= patch.z_drift * (scan_fraction((ny, nx)) - 0.5)
    out: FloatArray = q
    return out


def synthesize(
    surface: Surface,
    *,
    rows: int,
    cols: int,
    patch_size: tuple[float, float],
    pixels: tuple[int, int],
    overlap: tuple[float, float],
    start: tuple[float, float] = (0.0, 0.0),
    drift: DriftModel | None = None,
    seed: int = 0,
    bend: tuple[FloatArray, FloatArray] | None = None,
) -> list[SynthPatch]:
    """Scan ``surface`` as a ``rows x cols`` snake-ordered grid of drifting patches.

    Parameters
    ----------
    surface : Surface
        The sample in the stage frame.
    rows, cols : int
        Grid size.
    patch_size : (width, height)
        Scan range of a patch, metres; the pixel pitch is ``width / nx`` and ``height / ny``
        (the AFM convention).
    pixels : (nx, ny)
        Pixels per patch along x (fast axis) and y.
    overlap : (ox, oy)
        Fractions of the patch size shared with the neighbour.
    start : (x, y)
        Nominal origin of the first patch, metres.
    drift : DriftModel
        Error statistics (default: :meth:`DriftModel.typical`).
    seed : int
        Seed of all random draws.
    bend : ((nx,), (ny,)) arrays, optional
        The scanner's own displacement of every column along x and of every row along y,
        metres, the same in every patch (an open-loop piezo's hysteresis and creep): pixel
        ``(i, j)`` sees the sample at its nominal place plus ``(bend[0][j], bend[1][i])``.
    """
    nx, ny = pixels
    if nx < 2 or ny < 2:
        raise ValueError(f"need at least 2 x 2 pixels, got {pixels}")
    model = drift or DriftModel.typical()
    rng = np.random.default_rng(seed)
    plan = snake_grid(rows, cols, patch_size=patch_size, overlap=overlap, start=start)
    errs = model.draw(len(plan), rng)
    dx, dy = patch_size[0] / nx, patch_size[1] / ny
    frac = scan_fraction((ny, nx))
    bend_x, bend_y = (np.zeros(nx), np.zeros(ny)) if bend is None else bend
    if np.shape(bend_x) != (nx,) or np.shape(bend_y) != (ny,):
        raise ValueError(f"bend must be arrays of {nx} and {ny} values (columns, rows)")
    out = []
    for k, pp in enumerate(plan):
        x = pp.origin[0] + np.arange(nx) * dx
        y = pp.origin[1] + np.arange(ny) * dy
        xx, yy = np.meshgrid(x, y)
        xx, yy = xx + bend_x[None, :], yy + bend_y[:, None]
        centre = np.array([x[0] + 0.5 * (x[-1] - x[0]), y[0] + 0.5 * (y[-1] - y[0])])
        c, s = np.cos(errs.rotation[k]), np.sin(errs.rotation[k])
        R2 = np.array([[c, -s], [s, c]])
        t2 = centre + errs.stage_xy[k] - R2 @ centre
        wx = R2[0, 0] * xx + R2[0, 1] * yy + t2[0]
        wy = R2[1, 0] * xx + R2[1, 1] * yy + t2[1]
        h = surface.height(wx, wy)
        h = h + errs.z_offset[k] + errs.z_drift[k] * (frac - 0.5)
        h = h + rng.normal(0.0, model.line_noise, (ny, 1)) + rng.normal(0.0, model.noise, (ny, nx))
        R = np.eye(3)
        R[:2, :2] = R2
        t = np.array([t2[0], t2[1], -errs.z_offset[k]])
        out.append(
            SynthPatch(
                id=f"p{k:03d}",
                heights=h,
                origin=(float(x[0]), float(y[0])),
                pixel_size=(dx, dy),
                order=k,
                row=pp.row,
                col=pp.col,
                rotation=R,
                translation=t,
                z_drift=float(errs.z_drift[k]),
            )
        )
    return out
