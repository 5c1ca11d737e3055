"""The scanner's own distortion, shared by every patch: where its rows and columns really lie.

An open-loop scan piezo does not put its lines where the scan generator says. Its hysteresis
bends the ramp (a bow of a few per cent of the range between the rising and falling branches),
and creep after the long move back to a frame's first line keeps pulling the first lines on.
Every patch of a mosaic is scanned the same way, so every patch carries the same bend: row
``i`` lies at ``y0 + i dy + v(i)`` and column ``j`` at ``x0 + j dx + u(j)``. A rigid merge
cannot undo it (an overlap pairs the top rows of one patch, stretched, with the bottom rows of
the next, squeezed), and what it leaves shows as XY and Z errors between neighbours. Where the
scanner reads its own position (a Y sensor, as :func:`hardware.raster.linearize_rows` uses)
the rows are straightened at the source; this module measures the bend from the mosaic itself.

The measurement. Between two placed, overlapping patches ``a`` and ``b``, a band of ``a``'s
rows registers onto ``b`` with a shift ``s_y = v(i_a) - v(i_b) + c`` (``c``: what is left of
the pair's rigid error), where ``i_b`` is the row of ``b`` the band falls on. Over the bands
of every pair that is a linear system in ``v`` and one constant per pair. ``v`` is a sum of
Legendre polynomials of degree 2 and up in the row's place across the patch: an offset and a
scale (degrees 0 and 1) are not seen by overlaps of equal scans (the rigid transforms and the
controller's calibration hold them). Columns likewise, from bands of columns.

:func:`estimate_distortion` takes the patches and their transforms ``T_mosaic_patch`` and
returns the bend; :func:`undistort` resamples a patch's rows and columns to an even pitch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.polynomial import legendre
from numpy.typing import NDArray
from scipy import ndimage, special

from merge.core.overlap import moved_boxes, overlapping_pairs
from merge.core.patchset import Patch
from merge.core.transforms import PatchTransform

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Highest Legendre degree of each axis's bend (2: the hysteresis bow; 3 and 4: creep).
DEGREE = 4
#: Rows (columns) per band: each band's shift is one observation of the bend.
BAND = 2
#: Neighbouring bands are not independent: each samples the other scan through a cubic spline
#: four lines wide, so two bands of two lines share half their support. The covariance of the
#: bend is widened by this factor (measured: the chi-squared of straight scanners' bends came
#: out about twice its degrees of freedom without it).
BAND_CORRELATION = 2.0
#: Fewest valid pixels a band needs to register.
MIN_BAND_PIXELS = 12
#: Residuals beyond this many robust sigmas are dropped from the fit (a band on no texture).
REJECT = 4.0
#: A bend is taken out only where its coefficients differ from none beyond this quantile of
#: their chi-squared (so a straight scanner's patches are left as they were, not bent by noise).
SIGNIFICANCE = 0.999


@dataclass(frozen=True)
class ScanDistortion:
    """Displacement of every row and column from its nominal place, shared by all patches.

    rows : (ny,) metres along y (true minus nominal place) of each row.
    cols : (nx,) metres along x of each column.
    rows_sigma, cols_sigma : (ny,), (nx,) standard errors of those, metres.
    observations : bands that entered the fit (rows, columns).
    significant : whether each bend (rows, columns) stood out of its noise (see
        :data:`SIGNIFICANCE`); one that did not is zero.
    """

    rows: FloatArray
    cols: FloatArray
    rows_sigma: FloatArray
    cols_sigma: FloatArray
    observations: tuple[int, int]
    significant: tuple[bool, bool] = (True, True)

    @property
    def peak_to_valley(self) -> tuple[float, float]:
        """Largest minus smallest displacement along (x, y), metres."""
        return float(np.ptp(self.cols)), float(np.ptp(self.rows))


def _basis(place: FloatArray, n: int, degree: int) -> FloatArray:
    """(m, degree - 1) Legendre polynomials of degrees 2..degree at fractional ``place`` (m,)
    among ``n`` rows (columns): -1 at the first, +1 at the last."""
    t = 2.0 * np.asarray(place, dtype=np.float64) / (n - 1) - 1.0
    return np.asarray(legendre.legvander(t, degree)[:, 2:], dtype=np.float64)


@dataclass(frozen=True)
class _Surface:
    """A patch's heights as a cubic spline (holes filled with the mean) and where it has data.

    Not the refinement's look-ups (:class:`merge.refine.bank.SurfaceBank`, bilinear between the
    spline's half-pixel nodes): a band's shift rests on few lines, and on a grating's edges
    that interpolation's bias does not average out. Measured on the Nanonis bench's chessboard
    mosaic: bend along y 16.5 nm against 11.9 nm here, tile XY after the merge 5.2 against
    3.0 nm; on the folded sample both alike.
    """

    coef: FloatArray
    valid: FloatArray

    @classmethod
    def of(cls, patch: Patch) -> _Surface:
        h = np.asarray(patch.heights, dtype=np.float64)
        ok = np.isfinite(h)
        filled = np.where(ok, h, float(np.mean(h[ok])) if ok.any() else 0.0)
        return cls(ndimage.spline_filter(filled, order=3), ok.astype(np.float64))

    def sample(self, fi: FloatArray, fj: FloatArray) -> FloatArray:
        """Heights at fractional rows ``fi`` and columns ``fj``."""
        out: FloatArray = ndimage.map_coordinates(self.coef, [fi, fj], order=3, prefilter=False)
        return out


Observation = tuple[float, float, float, float]


def _band_shifts(
    a: Patch,
    ta: PatchTransform,
    b: Patch,
    tb: PatchTransform,
    surface: _Surface,
) -> tuple[list[Observation], list[Observation]]:
    """Shifts of ``a``'s bands of rows and of columns registered onto ``b`` (its ``surface``).

    Returns, for row bands and for column bands, ``(place_a, place_b, shift, variance)`` per
    band: the band's mean fractional row (column) in ``a`` and where it falls in ``b``; the
    shift along y (x), metres, of ``b``'s content against where the transforms put it; and
    that shift's variance.
    """
    ny, nx = a.shape
    (x0, y0), (dx, dy) = a.origin, a.pixel_size
    ii, jj = np.mgrid[0:ny, 0:nx].astype(np.float64)
    pts = np.column_stack([(x0 + jj * dx).ravel(), (y0 + ii * dy).ravel(), a.heights.ravel()])
    ok = np.isfinite(pts[:, 2])
    q = ta.apply(pts[ok])
    # into b's nominal frame: its rigid part inverted, then its drift plane taken off
    p = (q - tb.t) @ tb.R
    p[:, 2] -= (p[:, :2] - tb.centre) @ tb.slope
    (bx0, by0), (bdx, bdy) = b.origin, b.pixel_size
    fi, fj = (p[:, 1] - by0) / bdy, (p[:, 0] - bx0) / bdx
    bny, bnx = b.shape
    inside = (fi >= 1) & (fi <= bny - 2) & (fj >= 1) & (fj <= bnx - 2)
    fi, fj, z = fi[inside], fj[inside], p[inside, 2]
    near = ndimage.map_coordinates(surface.valid, [fi, fj], order=1) > 0.999
    if near.sum() < MIN_BAND_PIXELS:
        return [], []
    fi, fj, z = fi[near], fj[near], z[near]
    rows_a, cols_a = ii.ravel()[ok][inside][near], jj.ravel()[ok][inside][near]
    e = 0.5  # central differences of the spline, half a pixel either side
    h = surface.sample(fi, fj)
    gy = (surface.sample(fi + e, fj) - surface.sample(fi - e, fj)) / (2 * e * bdy)
    gx = (surface.sample(fi, fj + e) - surface.sample(fi, fj - e)) / (2 * e * bdx)
    # b's surface moved by s and lowered by c matches a's heights: h + g.s - c = z
    J = np.column_stack([gx, gy, -np.ones_like(h)])
    r = z - h
    out: tuple[list[Observation], list[Observation]] = ([], [])
    for axis, place_a, place_b in ((0, rows_a, fi), (1, cols_a, fj)):
        band = np.floor(place_a / BAND).astype(np.intp)
        count = np.bincount(band).astype(np.float64)
        used = np.flatnonzero(count >= MIN_BAND_PIXELS)
        if not len(used):
            continue

        def sums(v: FloatArray, band: IntArray = band, used: IntArray = used) -> FloatArray:
            return np.asarray(np.bincount(band, weights=v)[used], dtype=np.float64)

        # every band's normal equations at once: (bands, 3, 3) and (bands, 3)
        A = np.stack([[sums(J[:, i] * J[:, k]) for k in range(3)] for i in range(3)]).transpose(
            2, 0, 1
        )
        g = np.stack([sums(J[:, i] * r) for i in range(3)], axis=1)
        solvable = np.linalg.cond(A) < 1e12
        A, g, used = A[solvable], g[solvable], used[solvable]
        cov = np.linalg.inv(A)
        s = np.einsum("bij,bj->bi", cov, g)
        # residual sum of squares from the sums: r'r - s'g
        rss = np.maximum(sums(r * r)[solvable] - np.einsum("bi,bi->b", s, g), 0.0)
        k = 1 - axis  # the y shift for bands of rows, the x shift for bands of columns
        var = rss / (count[used] - 3) * cov[:, k, k]
        mean_a = sums(place_a)[solvable] / count[used]
        mean_b = sums(place_b)[solvable] / count[used]
        good = np.isfinite(var) & (var > 0)
        out[axis].extend(
            zip(
                mean_a[good].tolist(),
                mean_b[good].tolist(),
                s[good, k].tolist(),
                var[good].tolist(),
                strict=True,
            )
        )
    return out


def _pair_design(
    obs: list[list[Observation]], n: int, degree: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rows of the bend's least squares: design (m, degree - 1), shifts (m,), weights (m,).

    Each pair's own constant (what is left of its rigid error) is eliminated by centring its
    observations on their weighted mean; a pair with fewer than three bands says nothing."""
    designs, shifts, weights = [], [], []
    for pair in obs:
        if len(pair) < 3:
            continue
        place_a, place_b, shift, var = np.asarray(pair).T
        D = _basis(place_a, n, degree) - _basis(place_b, n, degree)
        w = 1.0 / var
        designs.append(D - (w @ D) / w.sum())
        shifts.append(shift - (w @ shift) / w.sum())
        weights.append(w)
    if not designs:
        return np.zeros((0, degree - 1)), np.zeros(0), np.zeros(0)
    return np.concatenate(designs), np.concatenate(shifts), np.concatenate(weights)


@dataclass(frozen=True)
class _AxisFit:
    values: FloatArray
    sigma: FloatArray
    bands: int
    significant: bool


def _fit(obs: list[list[Observation]], n: int, degree: int) -> _AxisFit:
    """The bend at each of ``n`` places, its sigma, and how many bands it rests on.

    Weighted least squares of the Legendre coefficients, twice more without the bands beyond
    :data:`REJECT` robust sigmas; the covariance is scaled by the fit's reduced chi-squared
    where that exceeds one (band variances that were too optimistic). No bend (zeros) where
    the bands do not determine every coefficient, or where the coefficients do not stand out
    of their covariance (:data:`SIGNIFICANCE`)."""
    D, y, w = _pair_design(obs, n, degree)
    k = degree - 1
    keep = np.ones(len(y), dtype=bool)
    coeffs: FloatArray = np.zeros(k)
    cov: FloatArray = np.zeros((k, k))
    for _ in range(3):
        Dw = D[keep] * w[keep, None]
        A = Dw.T @ D[keep]
        if keep.sum() <= k or np.linalg.matrix_rank(A) < k:
            return _AxisFit(np.zeros(n), np.zeros(n), 0, False)
        cov = np.asarray(np.linalg.inv(A), dtype=np.float64)
        coeffs = cov @ (Dw.T @ y[keep])
        z = (y - D @ coeffs) * np.sqrt(w)
        scale = 1.4826 * float(np.median(np.abs(z[keep])))
        keep = np.abs(z) < REJECT * max(scale, 1e-12)
    scale = BAND_CORRELATION * max(float(np.mean(((y - D @ coeffs) ** 2 * w)[keep])), 1.0)
    basis = _basis(np.arange(n, dtype=np.float64), n, degree)
    sigma = np.sqrt(np.einsum("ik,kl,il->i", basis, cov * scale, basis))
    distance = float(coeffs @ np.linalg.solve(cov * scale, coeffs))
    # the chi-square quantile with k degrees of freedom (scipy.stats, for this alone, took a
    # third of a second of every merging process's start)
    significant = distance > 2.0 * special.gammaincinv(0.5 * k, SIGNIFICANCE)
    values = basis @ coeffs if significant else np.zeros(n)
    return _AxisFit(values, sigma, int(keep.sum()), bool(significant))


def estimate_distortion(
    patches: Sequence[Patch],
    transforms: Sequence[PatchTransform],
    *,
    degree: int = DEGREE,
) -> ScanDistortion | None:
    """The rows' and columns' shared displacement, measured from every overlap.

    Parameters
    ----------
    patches : sequence of Patch
        Scans of one shape and pixel size (the bend is a property of that scan).
    transforms : sequence of PatchTransform
        ``T_mosaic_patch`` of each, from a merge (close enough that bands register).
    degree : int, keyword-only
        Highest Legendre degree of the bend (2 or more).

    Returns
    -------
    ScanDistortion, or None where the patches differ in shape or pixel size (no one bend).
    """
    if degree < 2:
        raise ValueError(f"degree must be 2 or more, got {degree}")
    if len(patches) != len(transforms):
        raise ValueError(f"{len(patches)} patches but {len(transforms)} transforms")
    if not patches:
        return None
    shape, pitch = patches[0].shape, patches[0].pixel_size
    if any(p.shape != shape or not np.allclose(p.pixel_size, pitch) for p in patches):
        return None
    pairs = overlapping_pairs(moved_boxes(np.array([p.footprint for p in patches]), transforms))
    ny, nx = shape
    surfaces = [_Surface.of(p) for p in patches]
    by_rows: list[list[Observation]] = []
    by_cols: list[list[Observation]] = []
    for ia, ib in pairs:
        for a, b in ((ia, ib), (ib, ia)):
            r, c = _band_shifts(patches[a], transforms[a], patches[b], transforms[b], surfaces[b])
            by_rows.append(r)
            by_cols.append(c)
    rows = _fit(by_rows, ny, min(degree, ny - 1))
    cols = _fit(by_cols, nx, min(degree, nx - 1))
    return ScanDistortion(
        rows.values,
        cols.values,
        rows.sigma,
        cols.sigma,
        (rows.bands, cols.bands),
        (rows.significant, cols.significant),
    )


def undistort(patch: Patch, distortion: ScanDistortion) -> Patch:
    """``patch`` resampled to an even pitch: row ``i`` of the result lies at ``y0 + i dy``.

    Heights more than half a pixel beyond the first or last measured line become NaN.
    """
    heights = np.asarray(patch.heights, dtype=np.float64)
    ny, nx = heights.shape
    if distortion.rows.shape != (ny,) or distortion.cols.shape != (nx,):
        raise ValueError(
            f"the distortion is of {len(distortion.rows)} x {len(distortion.cols)} px scans, "
            f"the patch {patch.id!r} has {ny} x {nx}"
        )
    dx, dy = patch.pixel_size
    out = _resample(heights, distortion.rows / dy, axis=0)
    out = _resample(out, distortion.cols / dx, axis=1)
    return replace(patch, heights=out)


def _resample(heights: FloatArray, offset: FloatArray, *, axis: int) -> FloatArray:
    """Lines along ``axis`` measured at places ``k + offset[k]``, brought back to places ``k``."""
    n = heights.shape[axis]
    index = np.arange(n, dtype=np.float64)
    where = index + offset
    if not np.all(np.diff(where) > 0):
        return heights
    data = np.moveaxis(heights, axis, 0)
    out = np.full_like(data, np.nan)
    inside = (index >= where[0] - 0.5) & (index <= where[-1] + 0.5)
    for j in range(data.shape[1]):
        col = data[:, j]
        ok = np.isfinite(col)
        if ok.sum() < 2:
            continue
        out[inside, j] = np.interp(index[inside], where[ok], col[ok])
    return np.moveaxis(out, 0, axis)
