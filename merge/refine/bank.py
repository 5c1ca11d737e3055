"""All patches of one refinement level as continuous surfaces, flattened for vectorized look-ups.

Lengths are in units of ``scale`` (the median pixel size), so the unknowns of the solver are of
order one. Every patch keeps its own frame: centred on its footprint, heights relative to its
median. Its points (every ``stride``-th pixel) and its heights and slopes (one row per pixel,
all patches end to end) feed the residuals of :mod:`merge.refine.normal_system`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.core.heightfield import Border, slope_noise, slopes, smooth_nan, upsample2
from merge.core.patchset import Patch

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Ints = NDArray[np.integer[Any]]

#: Arrays upsampled in one call: enough to spread the call's overhead, few enough that its
#: temporaries stay a few megabytes (large ones cost page faults on every allocation).
UPSAMPLE_BATCH = 16
#: Storage of the nodes (:attr:`SurfaceBank.surface`) and points (:attr:`SurfaceBank.points`).
SURFACE_DTYPE = np.float32
POINT_DTYPE = np.float32


class SurfaceBank:
    """Heights, slopes and points of every patch of one level (lengths in pixel units).

    Parameters
    ----------
    patches : sequence of Patch
    scale : float
        Unit of length, metres.
    smooth : float
        Gaussian smoothing of the heights, pixels (0: raw).
    stride : int
        Every ``stride``-th pixel of a patch along both axes is one of its points.
    border : {"mirror", "repeat"}, keyword-only
        How smoothing continues the heights beyond a patch's border
        (:func:`merge.core.heightfield.smooth_nan`): point-symmetrically (keeps slopes, doubles the
        border pixel's noise) or by repeating the border value (bends slopes that cross it).

    Look-ups are bilinear between nodes. Smoothed heights are smooth at the pixel scale, so the
    nodes are the pixels. Raw heights are not: between two pixels a bilinear look-up shaves off
    part of the roughness, the more the nearer the middle, which pulls every pair towards whole
    pixel offsets (TGX1 with 1.5 nm roughness at 1.3 pixels, noise-free: ±0.5 nm per pair). Their
    nodes are the cubic B-spline through the pixels at every half pixel
    (:func:`merge.core.heightfield.upsample2`), which cuts that error by half or more. Heights and
    slopes (central differences) go through the same interpolation, so the noise in a looked-up
    height stays uncorrelated with the noise in its slope (which would bias every step).
    Beyond its border a patch continues point-symmetrically; on roughness at the pixel scale
    that guess pushes a pair's nearest points apart a little (TGX1, noise-free: 0.1 nm per
    pair). Keeping look-ups a pixel inside the border removes that but costs more where
    overlaps are narrow (harsh TGX1 over 18 draws: map/floor mean 1.31 -> 1.34; a corner patch
    left with a sliver of overlap lost a fifth of its rows), so every look-up counts.
    """

    #: Nodes per pixel of the look-ups on raw heights.
    RAW_NODES = 2

    def __init__(
        self,
        patches: Sequence[Patch],
        scale: float,
        smooth: float,
        stride: int,
        *,
        border: Border = "mirror",
    ) -> None:
        n = len(patches)
        self.dx = np.array([p.pixel_size[0] / scale for p in patches])
        self.dy = np.array([p.pixel_size[1] / scale for p in patches])
        self.x0 = np.array([p.origin[0] / scale for p in patches])
        self.y0 = np.array([p.origin[1] / scale for p in patches])
        self.ny = np.array([p.shape[0] for p in patches], dtype=np.intp)
        self.nx = np.array([p.shape[1] for p in patches], dtype=np.intp)
        self.centre = np.zeros((n, 3))
        self.radius = np.zeros(n)
        self.half = np.zeros((n, 2))
        #: nodes per pixel of the look-ups
        self.nodes = self.RAW_NODES if smooth <= 0 else 1
        #: variance of a looked-up slope of unit white noise, per axis, in 1 / pixel²
        self.slope_noise = slope_noise(self.nodes)
        self.node_nx = (self.nx - 1) * self.nodes + 1
        self.node_ny = (self.ny - 1) * self.nodes + 1
        sizes = self.node_nx * self.node_ny
        self.offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
        # (nodes, 3): height, dh/dx, dh/dy of every node, so one gather fetches all three (a
        # row's three values side by side, one cache line), in float32: every node holds
        # heights relative to its patch's median in pixels, which float32 keeps to a millionth
        # of a pixel, and the nodes are most of a merge's memory (4 per pixel on raw heights)
        self.surface = np.empty((int(sizes.sum()), 3), dtype=SURFACE_DTYPE)
        self.point_start = np.zeros(n + 1, dtype=np.intp)
        pts, lines = [], []
        levelled: dict[int, FloatArray] = {}
        for c, p in enumerate(patches):
            h = p.heights / scale
            if smooth > 0:
                h = smooth_nan(h, smooth, border=border)
            ny, nx = h.shape
            w, hh = (nx - 1) * self.dx[c], (ny - 1) * self.dy[c]
            cx, cy = self.x0[c] + 0.5 * w, self.y0[c] + 0.5 * hh
            # the frame's height is the raw heights' median whatever the smoothing, so one
            # placement means the same on every level (a smoothed median moved up to 0.8 px on
            # TGX1's two-level faces: every level began with patches jumped in Z)
            self.centre[c] = (cx, cy, float(np.nanmedian(p.heights)) / scale)
            self.half[c] = (0.5 * w, 0.5 * hh)
            self.radius[c] = float(np.hypot(0.5 * w, 0.5 * hh))
            hl = h - self.centre[c, 2]
            if self.nodes > 1:
                levelled[c] = hl  # slopes come with the spline (_fill_spline_nodes)
            else:
                gx, gy = slopes(h, (self.dx[c], self.dy[c]))
                rows = slice(self.offset[c], self.offset[c] + sizes[c])
                for k, a in enumerate((hl, gx, gy)):
                    self.surface[rows, k] = a.ravel()
            ii, jj = np.meshgrid(np.arange(0, ny, stride), np.arange(0, nx, stride), indexing="ij")
            keep = np.isfinite(h[ii, jj])
            ii, jj = ii[keep], jj[keep]
            lines.append(ii.ravel().astype(np.int32))
            pts.append(
                np.column_stack(
                    [
                        self.x0[c] + jj * self.dx[c] - cx,
                        self.y0[c] + ii * self.dy[c] - cy,
                        hl[ii, jj],
                    ]
                ).astype(POINT_DTYPE)
            )
            self.point_start[c + 1] = self.point_start[c] + len(ii)
            if len(levelled) >= UPSAMPLE_BATCH or (levelled and c == n - 1):
                self._fill_spline_nodes(levelled)
                levelled = {}
        #: every point's place in its patch's frame and its height (m, 3), float32: a few
        #: millionths of a pixel, and look-ups take them back to float64
        self.points = np.concatenate(pts) if pts else np.empty((0, 3), dtype=POINT_DTYPE)
        #: the scan line (row of its patch) of every point
        self.line = np.concatenate(lines) if lines else np.empty(0, dtype=np.int32)
        #: the patch of every point
        self.owner = np.repeat(np.arange(n, dtype=np.int32), np.diff(self.point_start))

    def _fill_spline_nodes(self, heights: dict[int, FloatArray]) -> None:
        """Height, dh/dx and dh/dy at the half-pixel nodes of patches ``heights`` (by index),
        into :attr:`surface`.

        The heights through :func:`merge.core.heightfield.upsample2` (patches of one shape a
        call), with a pixel beyond the border; the slopes are central differences of the spline
        a pixel either side, ``(S(x + 1) - S(x - 1)) / 2``: by linearity the spline through the
        pixels' central differences, as the bilinear look-ups had them (at the border the
        one-sided difference, which the continuation beyond it makes of a central one).
        """
        shapes: dict[tuple[int, ...], list[int]] = {}
        for c, h in heights.items():
            shapes.setdefault(h.shape, []).append(c)
        for members in shapes.values():
            fine = upsample2(np.stack([heights[c] for c in members]), margin=1)
            for c, f in zip(members, fine, strict=True):
                rows = slice(self.offset[c], self.offset[c] + self.node_nx[c] * self.node_ny[c])
                self.surface[rows, 0] = f[2:-2, 2:-2].ravel()
                self.surface[rows, 1] = ((f[2:-2, 4:] - f[2:-2, :-4]) / (2.0 * self.dx[c])).ravel()
                self.surface[rows, 2] = ((f[4:, 2:-2] - f[:-4, 2:-2]) / (2.0 * self.dy[c])).ravel()

    def lookup(
        self, dst: Ints, p_local: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Height (local), slopes and validity of patch ``dst[i]`` under local point ``i``.

        Bilinear between the nodes; points outside the patch or next to a hole are not valid
        (their values are meaningless).
        """
        nx, ny = self.nx[dst], self.ny[dst]
        u = (p_local[:, 0] + self.half[dst, 0]) / self.dx[dst]
        v = (p_local[:, 1] + self.half[dst, 1]) / self.dy[dst]
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        if self.nodes > 1:
            u, v = u * self.nodes, v * self.nodes
            nx, ny = self.node_nx[dst], self.node_ny[dst]
        i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        fv, fu = np.clip(v - i0, 0.0, 1.0)[:, None], np.clip(u - j0, 0.0, 1.0)[:, None]
        k = self.offset[dst] + i0 * nx + j0
        a = self.surface  # take() gathers rows several times faster than fancy indexing
        a00, a01 = a.take(k, axis=0), a.take(k + 1, axis=0)
        a10, a11 = a.take(k + nx, axis=0), a.take(k + nx + 1, axis=0)
        top = a00 + fu * (a01 - a00)
        val = top + fv * (a10 + fu * (a11 - a10) - top)
        ok = inside & np.isfinite(val.sum(axis=1))
        return val[:, 0], val[:, 1], val[:, 2], ok

    def candidates(
        self, pairs: IntArray, R: FloatArray, s: FloatArray, margin: float
    ) -> tuple[Ints, Ints, Ints, IntArray]:
        """Points of every source patch that may fall on every destination patch.

        ``R`` (n, 3, 3) and ``s`` (n, 3) place every patch frame in the mosaic; ``margin``
        (pixel units) widens every outline. Returns per row the source patch, destination patch
        and global point index, plus the start of every directed pair's run of rows (runs are
        contiguous).
        """
        pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        # Both ways: the points of each patch against the other's surface, which averages the
        # interpolation of either surface (Jacobians act on both patches of a pair).
        src_all, dst_all = pairs.ravel(), pairs[:, ::-1].ravel()
        # every destination's outline in its source's local frame, all directed pairs at once
        hx, hy = self.half[dst_all, 0], self.half[dst_all, 1]
        corners = np.zeros((len(dst_all), 4, 3))
        corners[:, :, 0] = np.column_stack([-hx, hx, hx, -hx])
        corners[:, :, 1] = np.column_stack([-hy, -hy, hy, hy])
        Rsd = np.einsum("kji,kjl->kil", R[src_all], R[dst_all])
        loc = np.einsum("kij,kcj->kci", Rsd, corners)
        loc += np.einsum("kji,kj->ki", R[src_all], s[dst_all] - s[src_all])[:, None, :]
        lo = loc[:, :, :2].min(axis=1) - margin
        hi = loc[:, :, :2].max(axis=1) + margin
        x, y = self.points[:, 0], self.points[:, 1]
        # every source's points against all its destinations' outlines at once; the rows of
        # directed pair k are then a slice of its source's hits
        hits: list[IntArray] = [np.empty(0, dtype=np.intp)] * len(src_all)
        for src in np.unique(src_all).tolist():
            ks = np.flatnonzero(src_all == src)
            first, last = self.point_start[src], self.point_start[src + 1]
            px, py = x[first:last], y[first:last]
            inside = (
                (px >= lo[ks, 0, None])
                & (px <= hi[ks, 0, None])
                & (py >= lo[ks, 1, None])
                & (py <= hi[ks, 1, None])
            )
            col, pt = np.nonzero(inside)  # sorted by destination, then point
            bounds = np.searchsorted(col, np.arange(len(ks) + 1))
            for j, k in enumerate(ks.tolist()):
                hits[k] = pt[bounds[j] : bounds[j + 1]] + first
        counts = np.array([len(h) for h in hits], dtype=np.intp)
        kept = counts > 0
        if not kept.any():
            e = np.empty(0, dtype=np.intp)
            return e, e, e, np.zeros(1, dtype=np.intp)
        # one per row of the mosaic's system: int32 (points up to two billion), half the bytes
        return (
            np.repeat(src_all[kept].astype(np.int32), counts[kept]),
            np.repeat(dst_all[kept].astype(np.int32), counts[kept]),
            np.concatenate([h for h in hits if len(h)]).astype(np.int32),
            np.concatenate([[0], np.cumsum(counts[kept])]).astype(np.intp),
        )
