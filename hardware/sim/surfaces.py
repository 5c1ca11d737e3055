"""Sample surfaces placed in the stage frame: ``height(x, y)`` in metres for any points.

Every surface is deterministic for its seed and can be evaluated anywhere, so the same sample
serves the synthetic patch sets of the merge benchmark and the simulated instrument's scans.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]


class Surface(Protocol):
    """A sample topography in the stage frame."""

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Heights (metres) at stage positions ``x``, ``y`` (metres, any equal shapes)."""
        ...


def _gaussian_field(
    n: int, spacing: float, correlation: float, rng: np.random.Generator
) -> FloatArray:
    """A periodic ``n x n`` Gaussian random field with unit variance and the given correlation."""
    white = rng.standard_normal((n, n))
    k = np.fft.fftfreq(n, d=spacing) * 2.0 * np.pi
    kk = k[:, None] ** 2 + k[None, :] ** 2
    spectrum = np.exp(-kk * correlation**2 / 4.0)
    field = np.fft.ifft2(np.fft.fft2(white) * np.sqrt(spectrum)).real
    field -= field.mean()
    std = field.std()
    out: FloatArray = field / std if std > 0 else field
    return out


@dataclass(frozen=True)
class _Tile:
    """A periodic field sampled on a grid, evaluated by cubic B-spline interpolation."""

    coeffs: FloatArray
    spacing: float

    @classmethod
    def of(cls, values: FloatArray, spacing: float) -> _Tile:
        coeffs = ndimage.spline_filter(values, order=3, mode="grid-wrap")
        return cls(coeffs=coeffs, spacing=spacing)

    def __call__(self, x: FloatArray, y: FloatArray) -> FloatArray:
        xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        coords = np.stack([ya.ravel() / self.spacing, xa.ravel() / self.spacing])
        # periodic: fold into one period first (far or non-finite coordinates must never
        # reach the interpolator, which indexes with C integers)
        finite = np.isfinite(coords).all(axis=0)
        coords = np.where(finite, coords, 0.0) % np.asarray(self.coeffs.shape, float)[:, None]
        vals = ndimage.map_coordinates(
            self.coeffs, coords, order=3, mode="grid-wrap", prefilter=False
        )
        out: FloatArray = np.where(finite, vals, np.nan).reshape(xa.shape)
        return out


def _roughness(
    rms: float, correlation: float, seed: int, *, spacing: float = 5e-9, n: int = 1024
) -> _Tile | None:
    if rms <= 0:
        return None
    rng = np.random.default_rng(seed)
    return _Tile.of(rms * _gaussian_field(n, spacing, correlation, rng), spacing)


@dataclass(frozen=True)
class Chessboard:
    """A TGX1-like calibration grating: a chessboard of raised squares with rounded edges.

    Parameters
    ----------
    period : float
        Chessboard period (two squares), metres (TGX1: 3 µm).
    step : float
        Height of the raised squares, metres (TGX1: 0.6 µm).
    edge_width : float
        Horizontal extent of an edge from bottom to top, metres (~0.3 µm).
    roughness : float
        RMS of the fine roughness on every face, metres (~1.5 nm).
    roughness_correlation : float
        Correlation length of the roughness, metres.
    offset : (x, y)
        Stage position of a square corner, metres.
    seed : int
        Seed of the roughness.
    """

    period: float = 3e-6
    step: float = 0.6e-6
    edge_width: float = 0.3e-6
    roughness: float = 1.5e-9
    roughness_correlation: float = 25e-9
    offset: tuple[float, float] = (0.0, 0.0)
    seed: int = 0
    _rough: _Tile | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.period <= 0 or self.edge_width <= 0 or self.edge_width >= self.period / 2:
            raise ValueError("need period > 0 and 0 < edge_width < period / 2")
        tile = _roughness(self.roughness, self.roughness_correlation, self.seed)
        object.__setattr__(self, "_rough", tile)

    def _wave(self, u: FloatArray) -> FloatArray:
        # a smooth square wave in [-1, 1]: tanh of a sine, with the edge width set by beta
        beta = self.period / (np.pi * self.edge_width) * 1.5
        out: FloatArray = np.tanh(beta * np.sin(2 * np.pi * u / self.period)) / np.tanh(beta)
        return out

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64) - self.offset[0]
        ya = np.asarray(y, dtype=np.float64) - self.offset[1]
        h = 0.5 * self.step * (1.0 + self._wave(xa) * self._wave(ya))
        if self._rough is not None:
            h = h + self._rough(xa, ya)
        out: FloatArray = h
        return out


def tip_profile(r: FloatArray, radius: float, half_angle: float) -> FloatArray:
    """How far above its apex a tip's side lies at horizontal distance ``r`` (metres) from its
    axis: a sphere of ``radius`` at the apex, continued by the tangent cone of ``half_angle``
    (degrees from the axis) past ``r = radius cos(half_angle)``."""
    theta = math.radians(half_angle)
    rr = np.abs(np.asarray(r, dtype=np.float64))
    joint = radius * math.cos(theta)
    sphere = radius - np.sqrt(np.maximum(radius**2 - np.minimum(rr, joint) ** 2, 0.0))
    cone = radius * (1.0 - math.sin(theta)) + (rr - joint) / math.tan(theta)
    out: FloatArray = np.where(rr <= joint, sphere, cone)
    return out


@dataclass(frozen=True)
class TipDrawnChessboard:
    """A TGX1-like grating as an AFM tip draws it: raised squares with vertical walls, imaged
    by a tip of apex ``tip_radius`` on a cone of ``half_angle``. The image of a wall is the tip
    itself turned over (grey dilation of the sharp steps): flat tops rounded over the apex's
    radius at their edge, straight flanks at the cone's angle, and a kink where a flank meets
    the lower face; the flank spans about ``step * tan(half_angle)`` (:attr:`flank`).

    Parameters
    ----------
    period : float
        Chessboard period (two squares), metres (TGX1: 3 µm).
    step : float
        Height of the raised squares, metres.
    tip_radius : float
        Apex radius of the tip, metres (5-20 nm).
    half_angle : float
        Half-angle of the tip's cone, degrees (10-25).
    roughness, roughness_correlation : float
        RMS and correlation length of the faces' fine roughness, metres.
    offset : (x, y)
        Stage position of a square's corner, metres.
    seed : int
        Seed of the roughness.
    """

    period: float = 3e-6
    step: float = 0.6e-6
    tip_radius: float = 10e-9
    half_angle: float = 14.0
    roughness: float = 1.5e-9
    roughness_correlation: float = 25e-9
    offset: tuple[float, float] = (0.0, 0.0)
    seed: int = 0
    _rough: _Tile | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (self.period > 0 and self.step >= 0 and self.tip_radius > 0):
            raise ValueError("need period > 0, step >= 0 and tip_radius > 0")
        if not 0 < self.half_angle < 60:
            raise ValueError(f"half_angle must be in (0, 60) degrees, got {self.half_angle}")
        if self.flank >= self.period / 2:
            raise ValueError("the flanks (step * tan(half_angle)) must be narrower than a square")
        tile = _roughness(self.roughness, self.roughness_correlation, self.seed)
        object.__setattr__(self, "_rough", tile)

    @property
    def flank(self) -> float:
        """Horizontal extent of a drawn wall, from its top edge to its foot, metres (about
        ``step * tan(half_angle)``, the apex's arc added)."""
        theta = math.radians(self.half_angle)
        r = self.tip_radius
        joint = r * math.cos(theta)
        if self.step <= r * (1.0 - math.sin(theta)):  # the wall is lower than the apex's arc
            return math.sqrt(max(r**2 - (r - self.step) ** 2, 0.0))
        return joint + (self.step - r * (1.0 - math.sin(theta))) * math.tan(theta)

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64) - self.offset[0]
        ya = np.asarray(y, dtype=np.float64) - self.offset[1]
        a = self.period / 2
        i, j = np.floor(xa / a), np.floor(ya / a)
        u, v = xa - i * a, ya - j * a
        raised = (i + j) % 2 == 0
        # a low square's four edge neighbours are raised: the nearest wall's top edge is the
        # nearest side of the square (its diagonal neighbours are low)
        d = np.minimum(np.minimum(u, a - u), np.minimum(v, a - v))
        drawn = np.maximum(self.step - tip_profile(d, self.tip_radius, self.half_angle), 0.0)
        h = np.where(raised, self.step, drawn)
        if self._rough is not None:
            h = h + self._rough(xa, ya)
        out: FloatArray = h
        return out


@dataclass(frozen=True)
class FoldedSurface:
    """A folded organic surface (like the paper's microfossil): ridged folds on a swell.

    Parameters
    ----------
    fold_height : float
        Height scale of the folds, metres.
    fold_length : float
        Correlation length of the field whose zero lines become fold crests, metres.
    swell_height, swell_length : float
        Amplitude and correlation length of the long undulation, metres.
    roughness : float
        RMS of the fine roughness, metres.
    seed : int
    tile : float
        Period of the (periodic) fields, metres; make it larger than the sample area in use.
    """

    fold_height: float = 80e-9
    fold_length: float = 350e-9
    swell_height: float = 120e-9
    swell_length: float = 1.5e-6
    roughness: float = 1.0e-9
    roughness_correlation: float = 20e-9
    seed: int = 0
    tile: float = 10.24e-6
    _folds: _Tile = field(init=False, repr=False, compare=False)
    _swell: _Tile = field(init=False, repr=False, compare=False)
    _rough: _Tile | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        n_fold = max(64, round(self.tile / 10e-9))  # 10 nm samples of the fold field
        sp = self.tile / n_fold
        f = _gaussian_field(n_fold, sp, self.fold_length, rng)
        g = _gaussian_field(n_fold, sp, self.fold_length * 0.6, rng)
        # ridged noise: crests where f crosses zero, secondary wrinkles from g
        folds = (1.0 - np.abs(np.tanh(1.2 * f))) ** 2 + 0.35 * (1.0 - np.abs(np.tanh(g))) ** 2
        folds = (folds - folds.mean()) / folds.std()
        n_swell = 256
        swell = _gaussian_field(n_swell, self.tile / n_swell, self.swell_length, rng)
        object.__setattr__(self, "_folds", _Tile.of(self.fold_height * folds, sp))
        object.__setattr__(self, "_swell", _Tile.of(self.swell_height * swell, self.tile / n_swell))
        tile = _roughness(self.roughness, self.roughness_correlation, self.seed + 1)
        object.__setattr__(self, "_rough", tile)

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        h = self._folds(xa, ya) + self._swell(xa, ya)
        if self._rough is not None:
            h = h + self._rough(xa, ya)
        out: FloatArray = h
        return out


@dataclass(frozen=True)
class ImageSurface:
    """A measured height image placed in the stage frame, interpolated by cubic B-splines.

    Parameters
    ----------
    heights : (ny, nx) array
        Heights, metres, rows along y; NaN-free.
    pixel_size : (dx, dy)
        Metres.
    origin : (x, y)
        Stage position of pixel (0, 0), metres.

    Outside the image the height is NaN.
    """

    heights: FloatArray
    pixel_size: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    _coeffs: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        h = np.asarray(self.heights, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 4:
            raise ValueError(f"an image surface needs a 2-D array of at least 4 x 4, got {h.shape}")
        if not np.isfinite(h).all():
            h = np.where(np.isfinite(h), h, np.nanmedian(h))
        if self.pixel_size[0] <= 0 or self.pixel_size[1] <= 0:
            raise ValueError(f"pixel_size must be positive, got {self.pixel_size}")
        object.__setattr__(self, "heights", h)
        object.__setattr__(self, "_coeffs", ndimage.spline_filter(h, order=3, mode="mirror"))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the pixel centres, metres."""
        ny, nx = self.heights.shape
        x0, y0 = self.origin
        return x0, y0, x0 + (nx - 1) * self.pixel_size[0], y0 + (ny - 1) * self.pixel_size[1]

    def height(self, x: FloatArray, y: FloatArray) -> FloatArray:
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        u = (xa - self.origin[0]) / self.pixel_size[0]
        v = (ya - self.origin[1]) / self.pixel_size[1]
        ny, nx = self.heights.shape
        # outside is NaN anyway: keep far or non-finite coordinates from the interpolator
        coords = np.stack(
            [
                np.clip(np.nan_to_num(v.ravel()), -2, ny + 1),
                np.clip(np.nan_to_num(u.ravel()), -2, nx + 1),
            ]
        )
        vals = ndimage.map_coordinates(
            self._coeffs, coords, order=3, mode="mirror", prefilter=False
        )
        inside = (u >= -1e-9) & (u <= nx - 1 + 1e-9) & (v >= -1e-9) & (v <= ny - 1 + 1e-9)
        out: FloatArray = np.where(inside, vals.reshape(xa.shape), np.nan)
        return out


SURFACES = ("chessboard", "folded", "image")


# Surfaces are immutable and costly to build (their random fields): build each one once.
@functools.lru_cache(maxsize=8)
def _folded(seed: int, tile: float) -> FoldedSurface:
    return FoldedSurface(seed=seed, tile=tile)


@functools.lru_cache(maxsize=8)
def _chessboard(seed: int) -> Chessboard:
    return Chessboard(seed=seed)


def surface_by_name(
    name: str,
    *,
    seed: int = 0,
    image: str | None = None,
    pixel: tuple[float, float] | None = None,
    centred: bool = False,
    size: float | None = None,
) -> Surface:
    """A sample by name: ``chessboard``, ``folded`` or ``image`` (a 2-D ``.npy`` of heights in
    metres with its ``pixel`` size; ``centred`` puts its centre on the origin). ``size`` (metres)
    makes the folded surface's fields at least that large before they repeat.

    Raises ValueError (or OSError for an unreadable image) with a message that says what to fix.
    """
    if name == "chessboard":
        return _chessboard(seed)
    if name == "folded":
        tile = 10.24e-6 if size is None else 10.24e-6 * 2 ** math.ceil(math.log2(size / 10.24e-6))
        return _folded(seed, max(tile, 10.24e-6))
    if name != "image":
        raise ValueError(f"surface must be one of {', '.join(SURFACES)}, got {name!r}")
    if not image or not pixel:
        raise ValueError("an image surface needs an image file (.npy) and its pixel size")
    heights = np.load(image, allow_pickle=False)
    if heights.ndim != 2:
        raise ValueError(f"{image} must hold a 2-D height array, got shape {heights.shape}")
    ny, nx = heights.shape
    origin = (-(nx - 1) * pixel[0] / 2, -(ny - 1) * pixel[1] / 2) if centred else (0.0, 0.0)
    return ImageSurface(heights, pixel, origin=origin)
