"""The shift along a straight edge, measured on the texture beside it.

Where an overlap holds a straight edge (a grating's step) and a fine texture on the faces beside
it (its roughness), the texture measures the shift along the edge. But the correlation of
heights and slopes that found the peak is the edge's: a roughness of 1.5 nm beside a step of
600 nm weighs a ten-thousandth of its score, so along the edge the peak sits wherever noise and
the overlap's size put it, and that place was taken as measured wherever the information counted
the texture (:func:`merge.start.lattice.overlap_information`, its ``texture`` rule) or another
edge leaked into the overlap (a TGX1-like chessboard with 100 nm ramps at the paper's grid,
draw 1: a pair 152 nm off along its edge with a precision of 2 nm claimed, its patch merged
87 nm off).

So along every straight edge (:func:`merge.start.lattice.overlap_measurement`) the shift is measured
again on the texture alone: the heights less their smoothing, with the edges and a margin about
them masked (:func:`texture_image`), correlated near the edge's peak (:func:`along_edge`). Where
the texture's own peak does not stand out, nothing is measured along the edge.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from merge.core.heightfield import smooth_nan
from merge.start.lattice import coherence
from merge.start.ncc import masked_ncc
from merge.start.peaks import CorrelationPeak, find_peak

FloatArray = NDArray[np.float64]

#: Gaussian smoothing (cells) whose removal leaves the texture: the roughness at the cell's scale
#: stays, the edges' wide ramps and the faces' tilt go.
SMOOTH = 2.0
#: Cells whose smoothed slope exceeds this many times the image's median one are an edge's ...
STEEP = 4.0
#: ... and so are this many cells about them (what the smoothing's removal leaves of a ramp's
#: curvature reaches about as far).
MARGIN = 2
#: A texture more one-dimensional than this (:func:`merge.start.lattice.coherence`) is the
#: structure itself, not a roughness: the stripes of a grating a few cells wide outlive the
#: smoothing's removal, every shift along them scores 0.98, and such peaks moved a real
#: grating's pairs by up to 18 cells along its stripes. Roughness scores 0.1-0.3.
ISOTROPIC = 0.5


def texture_image(levelled: FloatArray) -> FloatArray | None:
    """The fine texture of a levelled image (h, w), same units: its heights less their
    smoothing over :data:`SMOOTH` cells, NaN on the edges (:data:`STEEP`, :data:`MARGIN`) and
    wherever the heights are missing; None where that is not a roughness (:data:`ISOTROPIC`)."""
    base = smooth_nan(levelled, SMOOTH)
    gy, gx = np.gradient(base)
    slope = np.hypot(gx, gy)
    typical = float(np.nanmedian(slope)) if np.isfinite(slope).any() else 0.0
    edge = ~np.isfinite(slope) | (slope > STEEP * typical)
    edge = ndimage.binary_dilation(edge, iterations=MARGIN)
    out: FloatArray = np.where(edge | ~np.isfinite(levelled), np.nan, levelled - base)
    return out if coherence(out) <= ISOTROPIC else None


def along_edge(
    ta: FloatArray,
    tb: FloatArray,
    peak: CorrelationPeak,
    direction: FloatArray,
    *,
    radius: float,
    min_overlap: int,
    accept: float,
    significance: float,
    ambiguity: float,
) -> float | None:
    """How far (cells, along the unit ``direction`` (x, y)) the texture's shift lies from the
    edge's ``peak`` of two levelled images, whose textures (:func:`texture_image`) are ``ta``
    and ``tb``; None where the correlation peak of the textures within ``radius`` cells does
    not count: at the window's border, with peaks within ``ambiguity`` of its score on its own
    ridge (:func:`merge.start.peaks.find_peak`), or scoring below ``accept`` without standing
    ``significance`` robust spreads above chance.
    """
    # correlated on what the search needs (a third of the transforms of the whole images): of
    # the first texture the cells the edge's peak overlaps, of the second those widened by
    # the search radius; the crops' shift is the images' plus ``off``
    dy, dx = peak.integer_shift
    reach = int(np.ceil(radius)) + 1
    rows_a = (max(0, -dy), min(ta.shape[0], tb.shape[0] - dy))
    cols_a = (max(0, -dx), min(ta.shape[1], tb.shape[1] - dx))
    if rows_a[1] - rows_a[0] < 2 or cols_a[1] - cols_a[0] < 2:
        return None
    rows_b = (max(0, rows_a[0] + dy - reach), min(tb.shape[0], rows_a[1] + dy + reach))
    cols_b = (max(0, cols_a[0] + dx - reach), min(tb.shape[1], cols_a[1] + dx + reach))
    off = (rows_a[0] - rows_b[0], cols_a[0] - cols_b[0])
    ncc, count, zero = masked_ncc(
        ta[rows_a[0] : rows_a[1], cols_a[0] : cols_a[1]],
        tb[rows_b[0] : rows_b[1], cols_b[0] : cols_b[1]],
    )
    found = find_peak(
        ncc,
        count,
        zero,
        expected=(float(dy + off[0]), float(dx + off[1])),
        radius=(radius, radius),
        min_overlap=min_overlap,
        ambiguity=ambiguity,
    )
    if found is None or found.at_border or found.ridge:
        return None
    if found.score < accept and found.excess < significance:
        return None
    moved = np.array(
        [found.shift[1] - off[1] - peak.shift[1], found.shift[0] - off[0] - peak.shift[0]]
    )
    return float(moved @ direction)
