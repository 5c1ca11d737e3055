"""Registration of a topography (a merged mosaic or one patch) onto an SEM image of the same
place, across the two modalities.

The SEM image is matched against the secondary-electron contrast the topography makes
(:func:`merge.correlative.contrast.se_features`, its weights fitted), coarse to fine from a
prior (the SEM-to-stage calibration's, or the nominal placement):

1. On a coarse grid of the SEM image (about 64 px across the mosaic), every rotation and scale
   of a grid around the prior, each with its best shift by masked normalised correlation of
   the tilt contrast (:func:`merge.correlative.correlate.masked_ncc`); the best kept, and the
   best match elsewhere (a rival: a periodic sample matches one period away; a lone edge
   matches all along itself, the rival then on a ridge of correlation joined to the best).
2. The same at finer grids around the best, with the fitted contrast (tilt and shading).
3. Gauss-Newton at the SEM's own pixels on the map and the contrast's weights together
   (least squares of SEM minus model), its covariance from the misfit and its correlation
   length, widened by what the model itself leaves open: the probe's reach (the next best
   reach's answer) and the topography's sampling (the answer on every other height).

The transform found, ``T_sem_mosaic``, maps a point of the mosaic (stage coordinates, metres)
to where the SEM image shows it (stage coordinates through the image's own pixel-to-stage
map): identity when the image's map is right. A match that cannot be trusted is returned with
``accepted`` false and the reason (no structure, two places alike, too little overlap, too
uncertain); input that cannot be registered at all raises :class:`RegistrationError`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from merge.correlative.contrast import FEATURES, se_features
from merge.correlative.correlate import Peak, best_peak, masked_ncc

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: The correlation of the fitted contrast with the SEM image under which a match is refused.
MIN_SCORE = 0.3
#: A rival match elsewhere this close to the best one makes the match ambiguous.
MAX_RIVAL = 0.9
#: The part of the mosaic that must lie inside the SEM image.
MIN_OVERLAP = 0.5
#: The standard deviation (SEM pixels) of where the mosaic's corners land past which a match
#: is too uncertain to use.
MAX_SIGMA_PX = 1.0
#: SEM pixels across the mosaic on the coarsest grid searched.
COARSE_PIXELS = 64
#: The reaches of the SEM's probe (SEM pixels, a Gaussian's standard deviation) over which
#: the model may see the slopes; the first is where the fit starts.
REACHES = (0.5, 0.25, 1.0)


class RegistrationError(ValueError):
    """Input that cannot be registered at all; the message says what is wrong."""


@dataclass(frozen=True)
class Similarity:
    """``p' = scale * R(rotation) @ p + offset`` (metres, degrees counter-clockwise)."""

    rotation_deg: float = 0.0
    scale: float = 1.0
    offset: tuple[float, float] = (0.0, 0.0)

    @property
    def matrix(self) -> FloatArray:
        a = math.radians(self.rotation_deg)
        c, s = math.cos(a), math.sin(a)
        return self.scale * np.array([[c, -s], [s, c]])

    def apply(self, points: FloatArray) -> FloatArray:
        """``points`` (..., 2) mapped."""
        out: FloatArray = np.asarray(points) @ self.matrix.T + np.asarray(self.offset)
        return out

    def invert(self, points: FloatArray) -> FloatArray:
        """The points that map to ``points`` (..., 2)."""
        out: FloatArray = (np.asarray(points) - np.asarray(self.offset)) @ np.linalg.inv(
            self.matrix
        ).T
        return out


@dataclass(frozen=True)
class SEMView:
    """An SEM image and where its pixels lie: ``stage = origin + matrix @ (column, row)``
    (metres; row 0 the top line)."""

    pixels: FloatArray
    origin: tuple[float, float]
    matrix: FloatArray

    @property
    def pixel(self) -> float:
        """The mean pixel size, metres."""
        return float(math.sqrt(abs(np.linalg.det(np.asarray(self.matrix)))))

    def to_stage(self, columns: FloatArray, rows: FloatArray) -> FloatArray:
        """Stage points (..., 2) of pixels."""
        q = np.stack(
            [np.asarray(columns, dtype=np.float64), np.asarray(rows, dtype=np.float64)], -1
        )
        out: FloatArray = q @ np.asarray(self.matrix).T + np.asarray(self.origin)
        return out

    def to_pixel(self, points: FloatArray) -> FloatArray:
        """Pixels (..., 2: column, row) of stage points (..., 2)."""
        inv = np.linalg.inv(np.asarray(self.matrix))
        out: FloatArray = (np.asarray(points) - np.asarray(self.origin)) @ inv.T
        return out


@dataclass(frozen=True)
class Registration:
    """Where the SEM shows the mosaic (:attr:`transform`, ``T_sem_mosaic``) and how sure.

    Attributes
    ----------
    sigma_rotation_deg, sigma_scale
        standard deviations of the rotation and scale.
    sigma_offset
        standard deviations of the offset's x and y, metres (the offset turns about
        the stage's origin, so it carries the rotation's uncertainty times the distance).
    sigma_here
        standard deviation of where the mosaic's centre is mapped, metres.
    score
        correlation of the fitted SE contrast with the SEM image over the mosaic (0..1).
    rival
        the best correlation of a match elsewhere on the coarse search, over the best.
    overlap
        the part of the mosaic inside the SEM image.
    affine
        (2, 3) the general affine map ``[A | t]`` when one was asked for, else None.
    weights
        the SE contrast's fitted weights (constant, tilt, slope x, slope y).
    """

    transform: Similarity
    sigma_rotation_deg: float
    sigma_scale: float
    sigma_offset: tuple[float, float]
    sigma_here: float
    score: float
    rival: float
    overlap: float
    accepted: bool
    reason: str | None
    iterations: int
    affine: FloatArray | None = None
    weights: tuple[float, ...] = field(default=())


@dataclass(frozen=True)
class _Topography:
    """The mosaic's contrast features at one blur, with the grid they lie on."""

    features: FloatArray  # (3, ny, nx)
    valid: BoolArray
    origin: tuple[float, float]
    pixel: tuple[float, float]

    def indices(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Fractional (row, column) of stage points (..., 2)."""
        return (
            (points[..., 1] - self.origin[1]) / self.pixel[1],
            (points[..., 0] - self.origin[0]) / self.pixel[0],
        )

    def sample(self, points: FloatArray, images: FloatArray) -> tuple[FloatArray, BoolArray]:
        """``images`` (k, ny, nx) at stage points (..., 2), and which points lie inside."""
        i, j = self.indices(points)
        ny, nx = self.valid.shape
        inside = (i >= 0) & (i <= ny - 1) & (j >= 0) & (j <= nx - 1)
        ii, jj = np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1)
        out = np.stack(
            [ndimage.map_coordinates(im, [ii, jj], order=1, mode="nearest") for im in images]
        )
        if self.complete:
            return out, inside
        measured = ndimage.map_coordinates(self.valid.astype(np.float64), [ii, jj], order=0)
        return out, inside & (measured > 0.5)

    @property
    def complete(self) -> bool:
        """Whether every height was measured."""
        return bool(self.valid.all())


def _topography(
    heights: FloatArray,
    origin: tuple[float, float],
    pixel: tuple[float, float],
    blur_m: float,
    reach_m: float = 0.0,
    *,
    sample_m: float,
) -> _Topography:
    """The contrast features blurred by ``blur_m`` metres, the slopes seen over ``reach_m``,
    for an SEM sampling every ``sample_m`` metres: heights coarser than that are first
    interpolated (cubic splines) onto a grid as fine, so the slopes the model takes are the
    surface's at the SEM's scale, not differences over the topography's wider pixels (those
    bias the match along the detector's direction, by about a tenth of a pixel)."""
    factor = min(4, math.ceil(math.sqrt(pixel[0] * pixel[1]) / sample_m - 0.05))
    if factor > 1:
        heights, pixel = _finer(heights, factor), (pixel[0] / factor, pixel[1] / factor)
    mean_pixel = math.sqrt(pixel[0] * pixel[1])
    features, valid = se_features(
        heights, pixel, blur=blur_m / mean_pixel, resolution=reach_m / mean_pixel
    )
    return _Topography(features, valid, origin, pixel)


def _finer(heights: FloatArray, factor: int) -> FloatArray:
    """``heights`` (ny, nx) on a grid ``factor`` times as fine, the same first and last
    points (cubic splines; NaN where the nearest height is)."""
    ny, nx = heights.shape
    rows = np.arange((ny - 1) * factor + 1) / factor
    cols = np.arange((nx - 1) * factor + 1) / factor
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    valid = np.isfinite(heights)
    filled = np.where(valid, heights, float(np.nanmedian(heights)))
    out: FloatArray = ndimage.map_coordinates(filled, [rr, cc], order=3, mode="nearest")
    if not valid.all():
        near = ndimage.map_coordinates(valid.astype(np.float64), [rr, cc], order=0)
        out[near < 0.5] = np.nan
    return out


def _grid(sem: SEMView, box: tuple[int, int, int, int], step: int) -> FloatArray:
    """Stage points (rows, columns, 2) of the centres of ``step`` x ``step`` blocks of the SEM
    pixels in ``box`` (column 0, row 0, columns, rows)."""
    c0, r0, nc, nr = box
    cc = c0 + (np.arange(nc // step) * step) + (step - 1) / 2
    rr = r0 + (np.arange(nr // step) * step) + (step - 1) / 2
    cols, rows = np.meshgrid(cc, rr)
    return sem.to_stage(cols, rows)


def _blocks(image: FloatArray, box: tuple[int, int, int, int], step: int) -> FloatArray:
    """The SEM pixels of ``box`` averaged over ``step`` x ``step`` blocks."""
    c0, r0, nc, nr = box
    h, w = nr // step, nc // step
    part = image[r0 : r0 + h * step, c0 : c0 + w * step]
    out: FloatArray = part.reshape(h, step, w, step).mean(axis=(1, 3))
    return out


def _search(
    topo: _Topography,
    sem: SEMView,
    image: FloatArray,
    points: FloatArray,
    start: Similarity,
    weights: FloatArray,
    *,
    rotations: FloatArray,
    scales: FloatArray,
    radius: int,
    step: int,
) -> tuple[Similarity, Peak]:
    """The best similarity of a grid of rotations and scales around ``start``, each with its
    best shift (up to ``radius`` grid pixels) by masked correlation."""
    best: tuple[Similarity, Peak] | None = None
    centre = points.reshape(-1, 2).mean(axis=0)
    contrast = np.tensordot(weights, topo.features, axes=1)  # (ny, nx) on the mosaic's grid
    for d_rot in rotations:
        for k_scale in scales:
            # turn and scale about the mosaic's centre as the SEM shows it
            trial = _about(start, centre, float(d_rot), float(k_scale))
            values, inside = topo.sample(trial.invert(points), contrast[None])
            template = values[0]
            mask = ndimage.binary_erosion(inside, iterations=1)
            mask[:radius, :] = mask[-radius:, :] = False
            mask[:, :radius] = mask[:, -radius:] = False
            if mask.sum() < 64:
                continue
            ncc = masked_ncc(template, mask, image, radius=radius)
            peak = best_peak(ncc, apart=max(3.0, radius / 4))
            if best is None or peak.score > best[1].score:
                shift = np.asarray(sem.matrix) @ np.array([peak.columns, peak.rows]) * step
                offset = (trial.offset[0] + shift[0], trial.offset[1] + shift[1])
                moved = Similarity(trial.rotation_deg, trial.scale, offset)
                best = (moved, peak)
    if best is None:
        raise RegistrationError("the mosaic covers too little of the SEM image to match")
    return best


def _about(t: Similarity, centre: FloatArray, d_rot: float, k_scale: float) -> Similarity:
    """``t`` followed by a turn of ``d_rot`` degrees and a scaling by ``k_scale`` about
    ``centre`` (SEM-side stage point)."""
    turn = Similarity(d_rot, k_scale, (0.0, 0.0))
    m = turn.matrix
    offset = m @ (np.asarray(t.offset) - centre) + centre
    return Similarity(
        t.rotation_deg + d_rot, t.scale * k_scale, (float(offset[0]), float(offset[1]))
    )


def _fit_weights(
    topo: _Topography, image: FloatArray, points: FloatArray, t: Similarity
) -> FloatArray:
    """The SE contrast's weights (constant, tilt, slope x, slope y) that best explain the SEM
    pixels at ``points`` with the mosaic placed by ``t``."""
    values, inside = topo.sample(t.invert(points), topo.features)
    if inside.sum() < 16:
        raise RegistrationError("the mosaic covers too little of the SEM image to match")
    design = np.column_stack([np.ones(int(inside.sum()))] + [v[inside] for v in values])
    weights, *_ = np.linalg.lstsq(design, image[inside], rcond=None)
    out: FloatArray = np.asarray(weights, dtype=np.float64)
    return out


@dataclass(frozen=True)
class _Fit:
    """What :func:`_refine` found: the inverse map ``p = b p' + c`` (metres), the covariance
    of its parameters (about ``centre``, scaled by ``span``), the contrast's weights, the
    iterations, and the SEM pixels used with their residuals."""

    b: FloatArray
    c: FloatArray
    cov: FloatArray
    centre: FloatArray
    span: float
    weights: FloatArray
    iterations: int
    mask: BoolArray
    residual: FloatArray


def _refine(
    topo: _Topography,
    image: FloatArray,
    points: FloatArray,
    start: Similarity,
    *,
    affine: bool,
    tolerance: float,
    callback: Callable[[int, float], None] | None,
    steps: int = 30,
    stride: int = 1,
) -> _Fit:
    """Gauss-Newton on the inverse map ``p = B (p' - centre) / span + c`` (linear in its
    entries; a similarity keeps ``B = [[a, -b], [b, a]]``) and the contrast's weights
    together, over the SEM pixels the mosaic covers at ``start``; converged when a step moves
    the mosaic less than ``tolerance`` metres. The residual's correlation area inflates the
    covariance. ``stride``: use every stride-th pixel each way only."""
    centre = points.reshape(-1, 2).mean(axis=0)
    span = float(np.ptp(points.reshape(-1, 2), axis=0).max()) or 1.0
    inv = np.linalg.inv(start.matrix)
    b_mat = inv * span
    c = inv @ (centre - np.asarray(start.offset))
    weights = _fit_weights(topo, image, points, start)
    _, covered = topo.sample(start.invert(points), topo.features[:1])
    footprint = ndimage.binary_erosion(covered, iterations=3)
    if stride > 1:  # every stride-th pixel each way: a quick approach to the minimum
        thin = np.zeros_like(footprint)
        thin[::stride, ::stride] = True
        footprint &= thin
    if footprint.sum() < 64:
        raise RegistrationError("the mosaic covers too little of the SEM image to match")
    local = (points[footprint] - centre) / span  # (n, 2) SEM-side points, of order one
    seen = image[footprint]
    n_geo = 6 if affine else 4
    iteration = 0

    def misfit(b_try: FloatArray, c_try: FloatArray, w_try: FloatArray, at: BoolArray) -> float:
        """Mean square misfit over the pixels ``at`` (one set for a step and its trials)."""
        values, inside = topo.sample(local[at] @ b_try.T + c_try, topo.features)
        if not inside.all():
            return math.inf
        model = w_try[0] + np.tensordot(w_try[1:], values, axes=1)
        return float(np.mean((seen[at] - model) ** 2))

    for iteration in range(1, steps + 1):
        model_images = np.concatenate([topo.features, _gradients(topo, weights)])
        values, use = topo.sample(local @ b_mat.T + c, model_images)
        if use.sum() < 64:
            raise RegistrationError("the mosaic covers too little of the SEM image to match")
        n_f = len(topo.features)
        f = values[:n_f, use]
        gx, gy = values[n_f, use], values[n_f + 1, use]
        ux, uy = local[use, 0], local[use, 1]
        residual = seen[use] - (weights[0] + np.tensordot(weights[1:], f, axes=1))
        if affine:  # p_x = b00 ux + b01 uy + cx, p_y = b10 ux + b11 uy + cy
            geometric = [gx * ux, gx * uy, gy * ux, gy * uy, gx, gy]
        else:  # b00 = b11 = a, b10 = -b01 = b
            geometric = [gx * ux + gy * uy, -gx * uy + gy * ux, gx, gy]
        design = np.column_stack([*geometric, np.ones_like(gx), *f])
        norms = np.maximum(np.linalg.norm(design, axis=0), 1e-300)
        scaled, *_ = np.linalg.lstsq(design / norms, residual, rcond=None)
        step = scaled / norms
        before = float(np.mean(residual**2))
        # the SEM image is sharper than any model of it: a full step overshoots; halve it
        # until the misfit falls (a backtracking line search)
        fraction = 1.0
        for _ in range(6):
            s_ = step * fraction
            if affine:
                b_try = b_mat + s_[:4].reshape(2, 2)
            else:
                b_try = b_mat + np.array([[s_[0], -s_[1]], [s_[1], s_[0]]])
            c_try, w_try = c + s_[n_geo - 2 : n_geo], weights + s_[n_geo:]
            if misfit(b_try, c_try, w_try, use) < before:
                break
            fraction /= 2
        else:
            break  # no step lowers the misfit: at its minimum
        b_mat, c, weights = b_try, c_try, w_try
        if callback is not None:
            callback(iteration, float(np.sqrt(before)))
        if float(np.abs(s_[:n_geo]).max()) < tolerance:
            break
    mask = np.zeros(footprint.shape, dtype=bool)
    mask[np.nonzero(footprint)[0][use], np.nonzero(footprint)[1][use]] = True
    kappa = _correlation_area(residual, mask)
    sigma2 = float(np.mean(residual**2)) * kappa
    normal = (design / norms).T @ (design / norms)
    cov = np.linalg.pinv(normal)[:n_geo, :n_geo] / np.outer(norms[:n_geo], norms[:n_geo]) * sigma2
    b_phys = b_mat / span
    c_phys: FloatArray = np.asarray(c - b_phys @ centre, dtype=np.float64)
    return _Fit(
        np.asarray(b_phys, dtype=np.float64),
        c_phys,
        cov,
        centre,
        span,
        weights,
        iteration,
        mask,
        residual,
    )


def _misfit(topo: _Topography, image: FloatArray, points: FloatArray, t: Similarity) -> float:
    """Mean square misfit of the contrast (its weights fitted) with the mosaic placed by
    ``t``, over the SEM pixels the mosaic covers."""
    values, inside = topo.sample(t.invert(points), topo.features)
    weights = _fit_weights(topo, image, points, t)
    model = weights[0] + np.tensordot(weights[1:], values, axes=1)
    return float(np.mean((image[inside] - model[inside]) ** 2))


def _gradients(topo: _Topography, weights: FloatArray) -> FloatArray:
    """The fitted contrast's gradient along the mosaic's x and y, per metre."""
    model = np.tensordot(weights[1:], topo.features, axes=1)
    gy, gx = np.gradient(model, topo.pixel[1], topo.pixel[0])
    return np.stack([gx, gy])


def _correlation_area(residual: FloatArray, mask: BoolArray) -> float:
    """Pixels per independent residual: the sum of the residual's normalised autocorrelation
    over lags up to 4 px (1 for white noise)."""
    image = np.zeros(mask.shape)
    image[mask] = residual - residual.mean()
    spectrum = np.fft.rfft2(image)
    auto = np.fft.irfft2(np.abs(spectrum) ** 2, s=mask.shape)
    weight = np.fft.irfft2(np.abs(np.fft.rfft2(mask.astype(np.float64))) ** 2, s=mask.shape)
    lags = np.arange(-4, 5)
    window = np.ix_(lags % mask.shape[0], lags % mask.shape[1])
    rho = auto[window] / np.maximum(weight[window], 1.0)
    rho = rho / max(float(rho[4, 4]), 1e-300)
    return float(max(1.0, np.sum(np.clip(rho, 0.0, None))))


def _similarity_of(b: FloatArray, c: FloatArray) -> Similarity:
    """The forward similarity of the inverse map ``p = b p' + c`` (its closest, for an
    affine ``b``)."""
    a = np.linalg.inv(b)  # p' = a p - a c
    u, _s, vt = np.linalg.svd(a)
    rot = u @ vt
    if np.linalg.det(rot) < 0:
        raise RegistrationError("the match mirrors the mosaic: the SEM image's map is flipped")
    angle = math.degrees(math.atan2(rot[1, 0], rot[0, 0]))
    scale = float(math.sqrt(abs(np.linalg.det(a))))
    offset = -a @ c
    return Similarity(angle, scale, (float(offset[0]), float(offset[1])))


def _sigmas(fit: _Fit, at: FloatArray, affine: bool) -> FloatArray:
    """Standard deviations of the rotation (degrees), the scale, the offset (x, y metres) and
    of where each mosaic point of ``at`` (k, 2) is mapped (x, y metres, point after point),
    through the covariance of the fit's parameters (numerical derivatives of
    :func:`_similarity_of`)."""
    local_b = fit.b * fit.span
    local_c = fit.c + fit.b @ fit.centre  # p = local_b (p' - centre) / span + local_c

    def values(x: FloatArray) -> FloatArray:
        if affine:
            lb, lc = local_b + x[:4].reshape(2, 2), local_c + x[4:6]
        else:
            lb, lc = local_b + np.array([[x[0], -x[1]], [x[1], x[0]]]), local_c + x[2:4]
        bb = lb / fit.span
        s = _similarity_of(bb, lc - bb @ fit.centre)
        here = s.apply(at).ravel()
        return np.array([s.rotation_deg, s.scale, *s.offset, *here])

    n = fit.cov.shape[0]
    base = values(np.zeros(n))
    jac = np.zeros((len(base), n))
    for k in range(n):
        h = max(float(np.sqrt(max(fit.cov[k, k], 0.0))), 1e-12)
        dx = np.zeros(n)
        dx[k] = h
        jac[:, k] = (values(dx) - values(-dx)) / (2 * h)
    out: FloatArray = np.sqrt(np.maximum(np.diag(jac @ fit.cov @ jac.T), 0.0))
    return out


def register_to_sem(
    heights: FloatArray,
    sem: SEMView,
    *,
    origin: tuple[float, float],
    pixel_size: tuple[float, float],
    prior: Similarity | None = None,
    search_rotation: float = 5.0,
    search_scale: float = 0.05,
    search_shift: float | None = None,
    affine: bool = False,
    callback: Callable[[int, float], None] | None = None,
) -> Registration:
    """Register a topography onto an SEM image.

    Parameters
    ----------
    heights : (ny, nx) array
        Heights, metres (NaN where not measured); row ``i``, column ``j`` at stage point
        ``origin + (j * dx, i * dy)``.
    sem : SEMView
        The SEM image and its pixel-to-stage map.
    origin, pixel_size : keyword-only, metres
    prior : Similarity, optional
        Where the SEM is expected to show the mosaic (default: where its map says).
    search_rotation, search_scale, search_shift : keyword-only
        How far from the prior to look: degrees, relative scale, metres (default: a fifth of
        the mosaic's size, 1 µm at least).
    affine : bool, keyword-only
        Fit a general affine map (shear, two scales) after the similarity.
    callback : callable, optional
        ``callback(iteration, rms)`` after every Gauss-Newton step.
    """
    h = np.asarray(heights, dtype=np.float64)
    image = np.asarray(sem.pixels, dtype=np.float64)
    if h.ndim != 2 or image.ndim != 2 or min(image.shape) < 32:
        raise RegistrationError(
            "need a 2-D topography and an SEM image of 32 x 32 px at least: "
            f"{h.shape}, {image.shape}"
        )
    if not np.isfinite(image).all():
        raise RegistrationError("the SEM image holds non-finite pixels")
    if not (0 < search_rotation <= 45 and 0 < search_scale <= 0.5):
        raise ValueError("search_rotation in (0, 45] degrees and search_scale in (0, 0.5]")
    prior = prior or Similarity()
    pixel = sem.pixel
    ny, nx = h.shape
    corners = (
        np.array(origin)
        + np.array([[0, 0], [nx - 1, 0], [0, ny - 1], [nx - 1, ny - 1]]) * pixel_size
    )
    size = float(np.ptp(corners, axis=0).max())
    shift = search_shift if search_shift is not None else max(1e-6, size / 5)
    seen = sem.to_pixel(prior.apply(corners))  # (4, 2) SEM pixels of the mosaic's corners
    lo, hi = seen.min(axis=0), seen.max(axis=0)
    rows_n, cols_n = image.shape
    inside = (np.clip(hi[0], 0, cols_n) - np.clip(lo[0], 0, cols_n)) * (
        np.clip(hi[1], 0, rows_n) - np.clip(lo[1], 0, rows_n)
    )
    overlap = float(inside / max((hi[0] - lo[0]) * (hi[1] - lo[1]), 1e-300))
    reach = shift / pixel + (size / pixel) * (math.radians(search_rotation) + search_scale)
    margin = math.ceil(reach) + 4
    c0, r0 = max(0, int(lo[0]) - margin), max(0, int(lo[1]) - margin)
    c1, r1 = (
        min(cols_n, math.ceil(hi[0]) + margin),
        min(rows_n, math.ceil(hi[1]) + margin),
    )
    if overlap < MIN_OVERLAP or c1 - c0 < 32 or r1 - r0 < 32:
        why = (
            f"only {overlap:.0%} of the mosaic lies in the SEM image ({MIN_OVERLAP:.0%} at "
            "least): acquire one over it"
        )
        return _refused(prior, overlap, why)
    box = (c0, r0, c1 - c0, r1 - r0)
    footprint = max(hi[0] - lo[0], hi[1] - lo[1])

    # 1. coarse: rotations and scales on a grid, each with its best shift
    step = max(1, int(footprint // COARSE_PIXELS))
    radius_m = shift + size * (math.radians(search_rotation) + search_scale) / 2
    best = prior
    rival, ridge, first = 0.0, False, True
    # the tilt contrast alone, until weights are fitted
    weights = np.zeros(len(FEATURES))
    weights[0] = 1.0
    d_rot = math.degrees(1.0 / max(footprint / step / 2, 4.0))
    rotations = np.arange(-search_rotation, search_rotation + 1e-9, d_rot)
    scales = 1.0 + np.arange(-search_scale, search_scale + 1e-9, d_rot * math.pi / 180)
    while True:
        topo = _topography(h, origin, pixel_size, 0.5 * pixel * step, sample_m=pixel * step)
        points = _grid(sem, box, step)
        blocks = _blocks(image, box, step)
        radius = min(math.ceil(radius_m / (pixel * step)) + 2, min(blocks.shape) // 2 - 2)
        if radius < 2:
            raise RegistrationError("the SEM image is too small around the mosaic to search")
        best, peak = _search(
            topo,
            sem,
            blocks,
            points,
            best,
            weights,
            rotations=rotations,
            scales=scales,
            radius=radius,
            step=step,
        )
        if first:  # the widest search tells whether another place matches alike
            rival = peak.rival / peak.score if peak.score > 0 else 1.0
            ridge = peak.ridge
            first = False
        fitted = _fit_weights(topo, blocks, points, best)
        weights = fitted[1:]
        if step <= 2:  # Gauss-Newton takes it from a pixel or two
            break
        step = max(1, step // 2)
        d_rot /= 2
        rotations = np.array([-d_rot, 0.0, d_rot]) * 2
        scales = 1.0 + np.array([-1.0, 0.0, 1.0]) * 2 * math.radians(d_rot)
        radius_m = 2 * pixel * step
    # 3. Gauss-Newton at the SEM's pixels, the slopes seen over each reach of the probe the
    # model may take: the reach that fits best is kept, the next best's answer measures the
    # model's own part of the uncertainty
    points = _grid(sem, box, 1)
    blocks = _blocks(image, box, 1)
    middle = np.asarray(origin) + np.array([nx - 1, ny - 1]) * np.asarray(pixel_size) / 2
    # the model sees no finer than the coarser of the two images' pixels
    coarse = max(pixel, math.sqrt(pixel_size[0] * pixel_size[1]))
    topos = {
        k: _topography(h, origin, pixel_size, 0.5 * pixel, k * coarse, sample_m=pixel)
        for k in REACHES
    }
    tol = 0.005 * pixel
    fit = _refine(
        topos[REACHES[0]],
        blocks,
        points,
        best,
        affine=affine,
        tolerance=tol,
        callback=callback,
        stride=2,
    )
    pose = _similarity_of(fit.b, fit.c)
    ranked = sorted(REACHES, key=lambda k: _misfit(topos[k], blocks, points, pose))
    fit = _refine(
        topos[ranked[0]], blocks, points, pose, affine=affine, tolerance=tol, callback=callback
    )
    topo = topos[ranked[0]]
    found = _similarity_of(fit.b, fit.c)
    other = _refine(
        topos[ranked[1]],
        blocks,
        points,
        found,
        affine=affine,
        tolerance=tol,
        callback=None,
        steps=6,
        stride=2,
    )
    second = _similarity_of(other.b, other.c)
    # the topography's own sampling biases the match (the SEM sees what falls between its
    # heights): the same fit on every other height moves by about that bias (it grows with
    # the pixel), which the uncertainty takes in
    sparse = _topography(
        h[::2, ::2],
        origin,
        (2 * pixel_size[0], 2 * pixel_size[1]),
        0.5 * pixel,
        ranked[0] * coarse,
        sample_m=pixel,
    )
    coarser = _refine(
        sparse, blocks, points, found, affine=affine, tolerance=tol, callback=None, steps=6
    )
    sampled = _similarity_of(coarser.b, coarser.c)
    # where the mosaic's centre and corners land: how sure, from the fit and from the model
    marks = np.vstack([middle[None], corners])
    sd = _sigmas(fit, marks, affine)
    model_rot = math.hypot(
        (second.rotation_deg - found.rotation_deg) / 2, sampled.rotation_deg - found.rotation_deg
    )
    model_at = np.hypot(
        np.hypot(*(second.apply(marks) - found.apply(marks)).T) / 2,
        np.hypot(*(sampled.apply(marks) - found.apply(marks)).T),
    )
    model_scale = math.hypot((second.scale - found.scale) / 2, sampled.scale - found.scale)
    stat_at = np.hypot(sd[4::2], sd[5::2])
    sd_rot = float(math.hypot(sd[0], model_rot))
    sd_scale = float(math.hypot(sd[1], model_scale))
    placed = np.hypot(stat_at, model_at)  # (5,) metres: the centre, then the corners
    sd_here, sd_worst = float(placed[0]), float(placed.max())
    values, _ = topo.sample(points @ fit.b.T + fit.c, topo.features)
    w = fit.weights
    model = w[0] + np.tensordot(w[1:], values, axes=1)
    mask = fit.mask
    score = float(np.corrcoef(model[mask], blocks[mask])[0, 1]) if mask.sum() > 2 else 0.0
    affine_map = None
    if affine:
        a = np.linalg.inv(fit.b)
        affine_map = np.column_stack([a, -a @ fit.c])
    reason = None
    if not np.isfinite(score) or score < MIN_SCORE:
        reason = (
            f"the SEM image and the mosaic's contrast correlate by {score:.2f} only "
            f"({MIN_SCORE} at least): too little structure, or not the same place"
        )
    elif rival > MAX_RIVAL and ridge:
        reason = (
            f"the match slides along the structure (a shift {rival:.0%} as good lies along "
            "it): the mosaic shows edges or lines one way only; take one that holds a corner "
            "or a feature both ways"
        )
    elif rival > MAX_RIVAL:
        reason = (
            f"two places match alike (the second {rival:.0%} of the best): a periodic "
            "sample; calibrate the SEM first so the search can be narrowed"
        )
    elif sd_worst > MAX_SIGMA_PX * pixel:
        reason = (
            f"the match is uncertain: the mosaic's corners placed within ± "
            f"{sd_worst / pixel:.2f} px ({MAX_SIGMA_PX} at most), rotation ± {sd_rot:.3f}°"
        )
    return Registration(
        transform=found,
        sigma_rotation_deg=sd_rot,
        sigma_scale=sd_scale,
        sigma_offset=(float(sd[2]), float(sd[3])),
        sigma_here=sd_here,
        score=score,
        rival=rival,
        overlap=overlap,
        accepted=reason is None,
        reason=reason,
        iterations=fit.iterations,
        affine=affine_map,
        weights=tuple(float(v) for v in w),
    )


def _refused(prior: Similarity, overlap: float, reason: str) -> Registration:
    return Registration(
        transform=prior,
        sigma_rotation_deg=math.inf,
        sigma_scale=math.inf,
        sigma_offset=(math.inf, math.inf),
        sigma_here=math.inf,
        score=0.0,
        rival=0.0,
        overlap=overlap,
        accepted=False,
        reason=reason,
        iterations=0,
    )
