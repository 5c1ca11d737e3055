"""The source's own smoothed slopes for the Jacobian, where its overlaps show they are better.

A row's Jacobian needs the surface's slope under its point. The destination's look-up gives
it a pixel either side of the foot (:meth:`merge.refine.bank.SurfaceBank.lookup`): sharp, but
on a face smooth at the pixel scale nearly all noise (a 1 µm grating's flat squares in 5 nm
pixels: roughness slopes ~0.06, the noise's ~0.1 per axis). A step's variance along a direction
only such faces hold grows with ``1 + e² / g²`` (slope noise over slope), and the solve counts
the noise's slopes as texture: the flat faces of 1 µm gratings carried 3 x the information
their signal holds, and their patches' XY missed the Cramér-Rao bound by 1.3-1.4 x.

A Gaussian derivative of the source at its own pixel estimates the same slope with a fraction
of the noise, and its odd kernel leaves the pixel's own height out, so its noise is
independent of the residual's (as the look-up's is). How wide a kernel helps depends on the
surface: on roughness at the pixel scale (the paper's grid) any smoothing takes signal with the
noise (flat-rough XY 1.29 -> 2.6 nm at 1.5 px everywhere). So the width is chosen by the
overlaps (:mod:`merge.refine.slope_widths`), or none; the rows then take the smoothed slopes
only where the surface is flat (:data:`FLAT`) and they agree with the look-up within
:data:`AGREE` times their typical difference: an edge or a defect, which smoothing blurs, keeps
its sharp slope.

Measured (10 draws, XY RMS nm, map over the floor median / worst): 1 µm grating ramp 50 nm,
period 3 µm, step 0.6 µm 0.238 -> 0.193, 1.188 -> 1.162, 1.578 -> 1.364 (8 draws before);
tgx1-1um 0.195 -> 0.169; the real 1-D grating (draws 0-7) 2.24 -> 1.45; MoS2 0.834 -> 0.779;
on the paper grid the overlaps choose no smoothing (its gratings, TGX1, flat-rough, the folded
surface as before, to the digit).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from merge.refine.runs import RowBlock

FloatArray = NDArray[np.float64]
#: Storage of a chosen patch's smoothed slopes (ny, nx, 2): they only tilt a Jacobian, as the
#: look-ups' float16 slopes between the build's passes do.
SLOPE_DTYPE = np.float16
#: Rows the smoothed slope replaces the look-up's on, at most this steep (dz/dx in lengths'
#: units): the faces between edges. On a ramp smoothing bends the slope most.
FLAT = 1.0
#: Where the smoothed and the looked-up slope differ by more than this many times their
#: typical difference, the surface has detail the smoothing blurs (an edge's foot, a defect):
#: the look-up's slope is kept (8 draws with a width chosen run by run: the real 1-D grating's
#: XY 2.50 nm with no such test, 1.72 at 2, 1.67 at 3; the 1 µm grating's 0.209 at 2, 0.190 at
#: 3, 0.188 with none).
AGREE = 3.0
#: Half-width of the Gaussian kernels, in widths (scipy's default).
TRUNCATE = 4.0


@dataclass(frozen=True)
class SourceSlopes:
    """The patches' smoothed slopes, each in its own frame, if the mosaic's overlaps chose a
    width (:func:`merge.refine.slope_widths.choose_source_slopes`).

    ``grids`` maps every patch to its slopes (ny, nx, 2: dz/dx, dz/dy per pixel, NaN where the
    kernel meets a hole or the border); ``spread2`` the typical mean square difference of the
    smoothed slopes to the destinations' look-ups (2 axes summed, the median patch's);
    ``noise_ratio`` the variance of a smoothed slope of white noise over a looked-up one's;
    ``width`` the kernel's standard deviation in pixels.
    """

    grids: dict[int, NDArray[np.float16]]
    spread2: float
    noise_ratio: float
    width: float

    def take(
        self, rows: RowBlock, ok: NDArray[np.bool_], grad: FloatArray, M: FloatArray
    ) -> NDArray[np.bool_]:
        """Put the chosen slopes into ``grad`` (m, 2; the destination's frame) in place, on the
        flat rows where they agree with it; ``M`` (k, 3, 3) the runs' maps from the source's
        frame to the destination's (:func:`merge.refine.rows.run_maps`). Returns (m,) which
        rows took them."""
        own = np.zeros(len(ok), dtype=bool)
        starts = rows.starts
        for k in range(len(starts) - 1):
            c = int(rows.src[starts[k]])
            grid = self.grids.get(c)
            if grid is None:
                continue
            lo, hi = starts[k], starts[k + 1]
            g = grid[rows.row[lo:hi], rows.col[lo:hi]].astype(np.float64)
            g = slopes_in_destination(g, np.broadcast_to(M[k], (hi - lo, 3, 3)))
            d2 = np.sum((g - grad[lo:hi]) ** 2, axis=1)
            with np.errstate(invalid="ignore"):
                use = ok[lo:hi] & (np.sum(g**2, axis=1) < FLAT**2)
                use &= d2 < AGREE**2 * self.spread2
            grad[lo:hi][use] = g[use]
            own[lo:hi] = use
        return own


def gaussian_slopes(heights: FloatArray, width: float, pitch: tuple[float, float]) -> FloatArray:
    """(ny, nx, 2) slopes (dz/dx, dz/dy) of ``heights`` (ny, nx; NaN in holes) by Gaussian
    derivatives of standard deviation ``width`` (pixels); ``pitch`` (dx, dy) in the heights'
    unit of length. NaN within the kernel's support (:data:`TRUNCATE` widths) of a hole, which
    is filled by the median, and wherever the heights mirrored beyond the border bring a pixel's
    own height into its slope (within half the support of the border): a slope that shares its
    point's noise biases every step, as the look-ups' one-sided differences at a border did
    (:func:`merge.refine.rows.residuals`). Nearer the border than the support, the mirrored
    heights bend the slope across it towards nought, which costs precision but no bias."""
    if width <= 0:
        raise ValueError(f"width must be positive, got {width}")
    if heights.ndim != 2:
        raise ValueError(f"heights must be 2-D, got shape {heights.shape}")
    hole = ~np.isfinite(heights)
    h = np.asarray(heights, dtype=np.float64)
    if hole.any():
        h = np.where(hole, np.nanmedian(heights) if not hole.all() else 0.0, heights)
    out = np.empty((*h.shape, 2))
    for k, order in enumerate(((0, 1), (1, 0))):
        out[..., k] = ndimage.gaussian_filter(
            h, width, order=order, mode="mirror", truncate=TRUNCATE
        )
        out[..., k] /= pitch[k] * _ramp_gain(width)
    reach = int(TRUNCATE * width + 0.5)  # the kernel's radius, as scipy makes it
    edge = reach // 2 + 1  # pixel d mirrors onto itself at offset 2d
    bad = np.ones(h.shape, dtype=bool)
    bad[edge:-edge, edge:-edge] = False
    if hole.any():
        bad |= ndimage.binary_dilation(hole, np.ones((3, 3), dtype=bool), iterations=reach)
    out[bad] = np.nan
    return out


@cache
def _ramp_gain(width: float) -> float:
    """The sampled Gaussian derivative's response to a unit ramp (a few parts in 10⁵ short of
    one at a width of a pixel): divided out, a plane's slope is exact."""
    reach = int(TRUNCATE * width + 0.5)
    ramp = np.arange(-reach, reach + 1, dtype=np.float64)
    return float(ndimage.gaussian_filter1d(ramp, width, order=1, truncate=TRUNCATE)[reach])


@cache
def gaussian_slope_noise(width: float) -> float:
    """Variance (per axis, in units of σ² / pixel²) of :func:`gaussian_slopes` of unit white
    noise, as :func:`merge.core.heightfield.slope_noise` gives a look-up's: the squared
    weights of the kernel, which holds no weight on its own pixel."""
    size = 2 * int(np.ceil(5 * width)) + 1
    impulse = np.zeros((size, size))
    impulse[size // 2, size // 2] = 1.0
    kernel = ndimage.gaussian_filter(
        impulse, width, order=(0, 1), mode="constant", truncate=TRUNCATE
    )
    return float(np.sum(kernel**2)) / _ramp_gain(width) ** 2


def slopes_in_destination(g: FloatArray, M: FloatArray) -> FloatArray:
    """(m, 2) slopes ``g`` (m, 2) of source surfaces in their own frames, as slopes in the
    destination's frames (drift plane included) through the maps ``M`` (m, 3, 3) of
    :func:`merge.refine.rows.run_maps`: a surface step ``(dx, dy, g · (dx, dy))`` maps to ``M``
    times it, so the slope there is ``dz' (d(x', y') / d(x, y))⁻¹``."""
    gx, gy = g[:, 0], g[:, 1]
    j11 = M[:, 0, 0] + M[:, 0, 2] * gx
    j12 = M[:, 0, 1] + M[:, 0, 2] * gy
    j21 = M[:, 1, 0] + M[:, 1, 2] * gx
    j22 = M[:, 1, 1] + M[:, 1, 2] * gy
    zx = M[:, 2, 0] + M[:, 2, 2] * gx
    zy = M[:, 2, 1] + M[:, 2, 2] * gy
    det = j11 * j22 - j12 * j21
    out: FloatArray = np.column_stack([zx * j22 - zy * j21, zy * j11 - zx * j12]) / det[:, None]
    return out
