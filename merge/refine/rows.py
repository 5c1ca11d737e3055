"""Every correspondence row of the normal system: its residual and its Jacobian.

A row is one point of a source patch over a destination patch, at the placement
:class:`PatchState` holds (pixel units). Rows come in runs, one per directed pair, so every run
moves its points with one small matrix product (:func:`residuals`, :func:`jacobians`) and sums
its information with another (:func:`segment_sums`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.refine.bank import SurfaceBank
from merge.refine.runs import RowBlock
from merge.refine.source_slopes import slopes_in_destination

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: Float arrays of any width (float32 where the mosaic's memory counts).
Floats = NDArray[np.floating[Any]]
#: Integer arrays of any width.
Ints = NDArray[np.integer[Any]]


@dataclass
class PatchState:
    """Where every patch is, in pixel units: ``q = R p_local + s + e_z (slope · p_local_xy)``.

    ``R`` (n, 3, 3) rotations, ``s`` (n, 3) the mosaic position of each patch frame's origin,
    ``slope`` (n, 2) the drift plane (dz/dx, dz/dy) of each patch.
    """

    R: FloatArray
    s: FloatArray
    slope: FloatArray


def run_maps(state: PatchState, a: Ints, b: Ints) -> tuple[FloatArray, FloatArray]:
    """Per run: the affine map ``p_b = M p_a + c`` from the source's frame to the destination's.

    ``q = R_a p + s_a + e_z (slope_a · p_xy)`` in the mosaic, then ``p_b = R_b' (q - s_b)``:
    ``M = R_b' (R_a + e_z [slope_a, 0])`` (k, 3, 3) and ``c = R_b' (s_a - s_b)`` (k, 3).
    """
    A = state.R[a]  # a gathered copy
    A[:, 2, :2] += state.slope[a]
    M = np.einsum("kji,kjl->kil", state.R[b], A)
    c = np.einsum("kji,kj->ki", state.R[b], state.s[a] - state.s[b])
    return M, c


def feet(
    bank: SurfaceBank, rows: RowBlock, state: PatchState
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Every row's point in its destination's frame: the runs' maps ``M`` (k, 3, 3) of
    :func:`run_maps`, the points (m, 3; one small matrix product per run) and whether the
    source holds a height there (m,; a hole's point is put at zero height)."""
    starts = rows.starts
    M, c = run_maps(state, rows.src[starts[:-1]], rows.dst[starts[:-1]])
    p_src = bank.point_xyz(rows)
    solid = np.isfinite(p_src[:, 2])
    p_src[~solid, 2] = 0.0
    p_dst = np.empty_like(p_src)
    for k in range(len(M)):
        lo, hi = starts[k], starts[k + 1]
        np.matmul(p_src[lo:hi], M[k].T, out=p_dst[lo:hi])
        p_dst[lo:hi] += c[k]
    return M, p_dst, solid


def heights_above(
    bank: SurfaceBank, dst: Ints, p_dst: FloatArray, slope: FloatArray, solid: NDArray[np.bool_]
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, FloatArray]:
    """Each point ``p_dst`` (m, 3; its destination's frame) above its destination ``dst``
    (m,)'s surface and drift plane ``slope`` (m, 2): the height (0 where not valid), whether
    it is valid (the source holds a height there, ``solid`` (m,), and the look-up hits) and the
    surface's slopes there (:meth:`SurfaceBank.lookup`)."""
    h, gx, gy, ok = bank.lookup(dst, p_dst)
    ok &= solid
    r = np.where(ok, p_dst[:, 2] - np.einsum("mi,mi->m", slope, p_dst[:, :2]) - h, 0.0)
    return r, ok, gx, gy


def residuals(
    bank: SurfaceBank, rows: RowBlock, state: PatchState
) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, NDArray[np.bool_]]:
    """Per row: residual, validity, the destination's normal slopes (m, 2), and whether they
    are the source's smoothed ones (:attr:`SurfaceBank.source_slopes`).

    Rows come in runs of one directed pair each (``rows.starts``), so every run moves its
    points with one small matrix product. The residual is the height of the source point above
    the destination's surface and drift plane; its gradient with respect to the mosaic position
    is the destination's normal ``(-slope_x, -slope_y, 1)``. A point in a hole is not valid.

    On the raw heights, within a pixel of the destination's border the slopes are the source's
    own at its point, taken into the destination's frame (:func:`slopes_in_destination`). The
    destination's there come from its continuation beyond the border: one-sided differences that
    share the border pixel's noise with the looked-up height (their product with the residual
    averages the noise's variance, not zero), and a slope correlated with its residual biases
    every step. Both ways of a pair have such a band, and their biases add. The source's slopes
    at its own border pixels are one-sided too, and are not used: taken everywhere, border
    included, they put 1 µm grating patches 0.78 nm off in XY (median of 4 draws; 0.32 with the
    destination's everywhere, 0.27 with the source's within the band). Within the band they are
    averaged over three lines (:meth:`SurfaceBank.point_slopes`), 3/8 of a lone central
    difference's noise variance: the bench's grating 0.71 -> 0.68 nm XY, worst map 1.92 ->
    1.87 x the floor. The coarse levels only bring patches near, on smoothed heights: the band
    there changed no result and cost 400 patches an iteration.
    """
    starts = rows.starts
    M, p_dst, solid = feet(bank, rows, state)
    slope = state.slope[rows.dst]
    r, ok, gx, gy = heights_above(bank, rows.dst, p_dst, slope, solid)
    grad = np.column_stack([gx, gy]) + slope
    if bank.nodes > 1:  # the raw heights' spline (the band, above)
        near = np.flatnonzero(ok & bank.near_border(rows.dst, p_dst))
        run = np.searchsorted(starts, near, side="right") - 1
        own = slopes_in_destination(bank.point_slopes(rows, near), M[run])
        known = np.isfinite(own).all(axis=1)
        grad[near[known]] = own[known]
    smoothed = np.zeros(len(r), dtype=bool)
    if bank.source_slopes is not None:  # where the overlaps chose them (merge.refine.slope_widths)
        smoothed = bank.source_slopes.take(rows, ok, grad, M)
    grad[~ok] = 0.0
    return r, ok, grad, smoothed


def lever_arms(points: FloatArray, rows: RowBlock, state: PatchState) -> FloatArray:
    """(m, 2) every row's point (``points`` (m, 3), :meth:`SurfaceBank.point_xyz`, holes at
    zero height) about its source patch's centre, in the mosaic's axes: the arm of its spin."""
    starts = rows.starts
    Ra = state.R[rows.src[starts[:-1]], :2, :]
    arm = np.empty((len(points), 2))
    for k in range(len(Ra)):
        lo, hi = starts[k], starts[k + 1]
        np.matmul(points[lo:hi], Ra[k].T, out=arm[lo:hi])
    return arm


def jacobians(
    bank: SurfaceBank,
    rows: RowBlock,
    state: PatchState,
    grad: Floats,
    ok: NDArray[np.bool_],
    arm: FloatArray,
    points: FloatArray,
) -> FloatArray:
    """(m, 6) derivative of every residual with respect to its source patch's unknowns.

    The translation part is the destination's normal in the mosaic, ``R_b (-grad, 1)``: one
    rotation per run; ``arm`` from :func:`lever_arms`, ``points`` as there.
    """
    starts = rows.starts
    nrm = np.column_stack([-grad, ok.astype(np.float64)])
    nrm[~ok] = 0.0
    m = np.empty_like(nrm)
    for k, b in enumerate(rows.dst[starts[:-1]]):
        lo, hi = starts[k], starts[k + 1]
        np.matmul(nrm[lo:hi], state.R[b].T, out=m[lo:hi])
    rho = bank.radius[rows.src, None]
    spin = (m[:, 1] * arm[:, 0] - m[:, 0] * arm[:, 1])[:, None]
    return np.concatenate([m, spin / rho, points[:, :2] / rho], axis=1)


def segment_sums(
    J: FloatArray, w: Floats, r: FloatArray, starts: IntArray
) -> tuple[FloatArray, FloatArray]:
    """Per run of rows ``starts[k]:starts[k + 1]``: ``Σ w J J'`` (k, 6, 6) and ``Σ w r J`` (k, 6).

    ``J`` (m, 6), ``w`` and ``r`` (m,); runs are non-empty and cover the rows from
    ``starts[0]`` on. One matrix product per run (runs hold hundreds of rows).
    """
    k = len(starts) - 1
    B, grad = np.empty((k, 6, 6)), np.empty((k, 6))
    wJ = J * w[:, None]
    for j in range(k):
        lo, hi = starts[j], starts[j + 1]
        B[j] = wJ[lo:hi].T @ J[lo:hi]
        grad[j] = r[lo:hi] @ wJ[lo:hi]
    return B, grad
