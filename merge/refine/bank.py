"""All patches of one refinement level as continuous surfaces, flattened for vectorized look-ups.

Lengths are in units of ``scale`` (the median pixel size), so the unknowns of the solver are of
order one. Every patch keeps its own frame: centred on its footprint, heights relative to its
median. Its points (every ``stride``-th pixel) and its heights (at every node, all patches end
to end) feed the residuals of :mod:`merge.refine.normal_system`. Only the nodes' heights are
stored: a slope is the difference of the heights a pixel either side, taken at the look-up
(:meth:`SurfaceBank.lookup`), and a point's place follows from its pixel and its height is the
node on it (:meth:`SurfaceBank.point_xyz`). Raw heights, four nodes per pixel, weigh 17 bytes
a pixel; with their slopes stored beside them they weighed 48.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from merge.core.heightfield import Border, slope_noise, smooth_nan, upsample2
from merge.core.patchset import Patch
from merge.core.progress import checkpoint
from merge.refine.kinked import KinkedCells
from merge.refine.runs import RowBlock, Runs

if TYPE_CHECKING:
    from merge.refine.source_slopes import SourceSlopes

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Ints = NDArray[np.integer[Any]]

#: Arrays upsampled in one call: enough to spread the call's overhead, few enough that its
#: temporaries stay a few megabytes (large ones cost page faults on every allocation).
UPSAMPLE_BATCH = 16
#: Share of a run's points (its outline's, without margin) that a border band must leave it,
#: else the run keeps all its points (:meth:`SurfaceBank.candidates`).
BAND_KEEPS = 0.5
#: Storage of the nodes' heights (:attr:`SurfaceBank.height`): float32 keeps heights relative
#: to a patch's median, in pixels, to a millionth of a pixel.
SURFACE_DTYPE = np.float32


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

    Near a kink (a tip-drawn edge's foot or top: straight flanks meeting flat faces) the spline
    rings by a share of the slope's jump times the pixel, differently in every patch as the kink
    falls elsewhere between its pixels; there the raw look-ups draw the straight pieces and the
    kink where they meet (:mod:`merge.refine.kinked`, :mod:`merge.core.kinks`). The paper's grid
    on a tip-drawn chessboard (0.6 µm steps, 157 nm flanks, 20 nm pixels), 1 nm noise, seeds
    21-23: XY 1.36 -> 0.83 nm; noise-free from the true places 0.73 -> 0.17 nm (what is left is
    the faces' roughness between the pixels).
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
        self.half = np.column_stack([0.5 * (self.nx - 1) * self.dx, 0.5 * (self.ny - 1) * self.dy])
        self.radius = np.hypot(self.half[:, 0], self.half[:, 1])
        #: every ``stride``-th pixel is a point
        self.stride = stride
        #: rows and columns of every patch's point grid
        self.point_ny = (self.ny + stride - 1) // stride
        self.point_nx = (self.nx + stride - 1) // stride
        #: the first point of every patch, and (last) their count, holes included
        self.point_start = np.concatenate([[0], np.cumsum(self.point_ny * self.point_nx)])
        #: points per patch that hold a height (its weight in the gauge; the spline of raw
        #: heights has none within a pixel of a hole)
        self.point_count = np.zeros(n, dtype=np.intp)
        #: nodes per pixel of the look-ups
        self.nodes = self.RAW_NODES if smooth <= 0 else 1
        #: variance of a looked-up slope of unit white noise, per axis, in 1 / pixel²
        self.slope_noise = slope_noise(self.nodes)
        #: the patches' own smoothed slopes, where the raw level's overlaps chose them
        #: (:mod:`merge.refine.slope_widths`): the Jacobians take them instead of the look-ups'
        self.source_slopes: SourceSlopes | None = None
        self.node_nx = (self.nx - 1) * self.nodes + 1
        self.node_ny = (self.ny - 1) * self.nodes + 1
        #: every patch's nodes are stored with a pixel's worth of them beyond every border (the
        #: heights continued point-symmetrically), so a slope is a central difference
        #: everywhere: row length of the stored grid, and the index of interior node (0, 0)
        self.grid_nx = self.node_nx + 2 * self.nodes
        sizes = self.grid_nx * (self.node_ny + 2 * self.nodes)
        offset = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
        self.origin = offset + self.nodes * (self.grid_nx + 1)
        # the nodes are most of a merge's memory: float32, relative to the patch's median
        self.height = np.empty(int(sizes.sum()), dtype=SURFACE_DTYPE)
        #: raw heights: the cells near a kink, where look-ups draw straight pieces
        self.kinks = KinkedCells(self.ny, self.nx) if self.nodes > 1 else None
        levelled: dict[int, FloatArray] = {}
        for c, p in enumerate(patches):
            h = p.heights / scale
            if smooth > 0:
                h = smooth_nan(h, smooth, border=border)
            cx, cy = self.x0[c] + self.half[c, 0], self.y0[c] + self.half[c, 1]
            # the frame's height is the raw heights' median whatever the smoothing, so one
            # placement means the same on every level (a smoothed median moved up to 0.8 px on
            # TGX1's two-level faces: every level began with patches jumped in Z)
            self.centre[c] = (cx, cy, p.median_height / scale)
            hl = h - self.centre[c, 2]
            if self.nodes > 1:
                levelled[c] = hl  # upsampled in batches (_fill_spline_nodes)
                if self.kinks is not None:
                    self.kinks.add(c, hl)
            else:
                # continued point-symmetrically: the central difference at the border is then
                # the one-sided one
                grid = np.pad(hl, 1, mode="reflect", reflect_type="odd")
                self.height[offset[c] : offset[c] + sizes[c]] = grid.ravel()
            if len(levelled) >= UPSAMPLE_BATCH or (levelled and c == n - 1):
                self._fill_spline_nodes(levelled, offset)
                levelled = {}
            if c % UPSAMPLE_BATCH == 0:
                checkpoint()  # 10,000 patches' nodes take seconds: a cancel stops here
        step, m = stride * self.nodes, self.nodes
        for c in range(n):
            at = self.grid(c)[m:-m:step, m:-m:step]
            self.point_count[c] = int(np.isfinite(at).sum())

    def _fill_spline_nodes(self, heights: dict[int, FloatArray], offset: IntArray) -> None:
        """The half-pixel nodes of patches ``heights`` (by index) into :attr:`height`, from
        ``offset`` on, a pixel beyond every border included.

        The heights through :func:`merge.core.heightfield.upsample2` (patches of one shape a
        call), which continues them point-symmetrically beyond the border. The slopes the
        look-ups take from them are central differences of the spline a pixel either side,
        ``(S(x + 1) - S(x - 1)) / 2``: by linearity the spline through the pixels' central
        differences, as bilinear look-ups between pixels had them (at the border the one-sided
        difference, which the continuation makes of a central one).
        """
        shapes: dict[tuple[int, ...], list[int]] = {}
        for c, h in heights.items():
            shapes.setdefault(h.shape, []).append(c)
        for members in shapes.values():
            fine = upsample2(np.stack([heights[c] for c in members]), margin=1)
            for c, f in zip(members, fine, strict=True):
                self.height[offset[c] : offset[c] + f.size] = f.ravel()

    def lookup(
        self, dst: Ints, p_local: FloatArray, *, reach: int | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Height (local), slopes and validity of patch ``dst[i]`` under local point ``i``.

        Bilinear between the nodes; points outside the patch or next to a hole are not valid
        (their values are meaningless). The slopes are differences ``reach`` nodes either side
        (default a pixel's worth); one node is the sharpest the look-up's heights have.
        """
        reach = self.nodes if reach is None else reach
        if not 1 <= reach <= self.nodes:
            raise ValueError(f"reach must be 1 to {self.nodes} nodes, got {reach}")
        nx, ny = self.nx[dst], self.ny[dst]
        u, v = self._pixel_coords(dst, p_local)
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        if self.nodes > 1:
            u, v = u * self.nodes, v * self.nodes
            nx, ny = self.node_nx[dst], self.node_ny[dst]
        i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        fv, fu = np.clip(v - i0, 0.0, 1.0), np.clip(u - j0, 0.0, 1.0)
        row = self.grid_nx[dst]
        k = self.origin[dst] + i0 * row + j0
        h = self._bilinear(k, row, fu, fv)
        if self.kinks is not None:
            self.kinks.redraw(self, dst, u / self.nodes, v / self.nodes, inside, h)
        # slopes: the bilinear look-ups a pixel either side (by linearity, the bilinear
        # interpolation of the nodes' central differences)
        span = 2.0 * reach / self.nodes  # pixels
        gx = self._bilinear(k + reach, row, fu, fv)
        gx -= self._bilinear(k - reach, row, fu, fv)
        gx /= span * self.dx[dst]
        gy = self._bilinear(k + reach * row, row, fu, fv)
        gy -= self._bilinear(k - reach * row, row, fu, fv)
        gy /= span * self.dy[dst]
        ok = inside & np.isfinite(h) & np.isfinite(gx) & np.isfinite(gy)
        return h, gx, gy, ok

    def _pixel_coords(self, dst: Ints, p_local: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Local points ``i`` in pixels of patch ``dst[i]`` (column, row; 0 at its first)."""
        u: FloatArray = (p_local[:, 0] + self.half[dst, 0]) / self.dx[dst]
        v: FloatArray = (p_local[:, 1] + self.half[dst, 1]) / self.dy[dst]
        return u, v

    def near_border(self, dst: Ints, p_local: FloatArray) -> NDArray[np.bool_]:
        """(m,) whether the look-up of local point ``i`` on patch ``dst[i]`` falls within a pixel
        of its border. There the slopes come from the nodes the continuation beyond the border
        made of the border pixels (one-sided differences), so their noise is the looked-up
        height's own."""
        u, v = self._pixel_coords(dst, p_local)
        out: NDArray[np.bool_] = (
            (u < 1.0) | (v < 1.0) | (u > self.nx[dst] - 2.0) | (v > self.ny[dst] - 2.0)
        )
        return out

    def point_slopes(self, rows: RowBlock, at: IntArray) -> FloatArray:
        """(len(at), 2) the slopes (dz/dx, dz/dy, in its source's frame) at the points of rows
        ``at``: central differences a pixel either side, averaged over the point's line and
        the two beside it with weights 1/4, 1/2, 1/4 (Sobel's), none of which holds the point's
        own height, so they share no noise with it. NaN on the source's border pixels (one-sided
        there, so they do) and next to a hole.

        The average across: a central difference alone has a noise variance of 1/2 per pitch²
        (unit white noise), more than twice the 2/9 of a look-up between the spline's nodes;
        averaged over three lines it is 3/16.
        """
        c, row, col = rows.src[at], rows.row[at], rows.col[at]
        node = self._node(c, row, col)
        a = self.height
        m = np.full(len(at), self.nodes)
        line = self.nodes * self.grid_nx[c]
        out = np.zeros((len(at), 2))
        for k, (step, across) in enumerate(((m, line), (line, m))):
            for beside, weight in ((0, 0.5), (across, 0.25), (-across, 0.25)):
                ahead, behind = a.take(node + beside + step), a.take(node + beside - step)
                out[:, k] += weight * (ahead.astype(np.float64) - behind)
        out /= 2.0 * np.column_stack([self.dx[c], self.dy[c]])
        border = (row == 0) | (col == 0) | (row == self.ny[c] - 1) | (col == self.nx[c] - 1)
        out[border] = np.nan
        return out

    def grid(self, c: int) -> NDArray[np.float32]:
        """Patch ``c``'s stored nodes (rows, :attr:`grid_nx`), a pixel's worth beyond every border
        included (a view, float32)."""
        first = self.origin[c] - self.nodes * (self.grid_nx[c] + 1)
        rows = self.node_ny[c] + 2 * self.nodes
        out: NDArray[np.float32] = self.height[first : first + rows * self.grid_nx[c]]
        return out.reshape(rows, -1)

    def _bilinear(self, k: IntArray, row: IntArray, fu: FloatArray, fv: FloatArray) -> FloatArray:
        """Bilinear between nodes ``k``, ``k + 1``, ``k + row``, ``k + row + 1`` (m,) at
        fractions ``fu`` (along a row) and ``fv``."""
        a = self.height  # take() gathers several times faster than fancy indexing
        h00, h01 = a.take(k).astype(np.float64), a.take(k + 1)
        h10, h11 = a.take(k + row), a.take(k + row + 1)
        top = h00 + fu * (h01 - h00)
        out: FloatArray = top + fv * (h10 + fu * (h11 - h10) - top)
        return out

    def candidates(
        self, pairs: IntArray, R: FloatArray, s: FloatArray, margin: float, *, band: float = 0.0
    ) -> Runs:
        """Points of every source patch that may fall on every destination patch.

        ``R`` (n, 3, 3) and ``s`` (n, 3) place every patch frame in the mosaic; ``margin``
        (pixel units) widens every outline. Both ways: the points of each patch against the
        other's surface, which averages the interpolation of either surface (Jacobians act on
        both patches of a pair). Returns one run per directed pair whose rectangle holds a point:
        the source's points within the destination's outline (its bounding box in the source's
        frame), the runs of each source one after another.

        ``band`` (pixels): only the points of a run that far from both patches' borders (the
        destination's outline narrowed by it, not widened by ``margin``), where that leaves it
        :data:`BAND_KEEPS` of the points within the outline; else all of them (a narrow overlap
        has none to spare). Smoothed heights near a border are partly the smoothing of the
        heights' continuation beyond it, a guess that biases every pair, as patches overlap
        along their borders (the widest level of :data:`merge.refine.icp.DEFAULT_LEVELS`).
        """
        pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        src, dst = pairs.ravel(), pairs[:, ::-1].ravel()
        box, count = self._boxes(src, dst, R, s, margin=margin)
        if band > 0:
            inner, inner_count = self._boxes(src, dst, R, s, inset=band)
            narrowed = inner_count >= BAND_KEEPS * self._boxes(src, dst, R, s)[1]
            box[narrowed], count[narrowed] = inner[narrowed], inner_count[narrowed]
        kept = np.flatnonzero(count > 0)
        if not len(kept):
            return Runs.empty()
        # the runs of one source together: its scan lines' offsets are shared by all of them
        kept = kept[np.argsort(src[kept], kind="stable")]
        return Runs(
            src[kept],
            dst[kept],
            box[kept],
            np.concatenate([[0], np.cumsum(count[kept])]).astype(np.intp),
        )

    def _boxes(
        self,
        src: IntArray,
        dst: IntArray,
        R: FloatArray,
        s: FloatArray,
        *,
        margin: float = 0.0,
        inset: float = 0.0,
    ) -> tuple[IntArray, IntArray]:
        """Per directed pair: the rectangle (k, 4: rows ``[i0, i1)``, columns ``[j0, j1)``) of
        the source's point grid within the destination's outline widened by ``margin`` (pixel
        units), or narrowed by ``inset`` pixels and as far from the source's own border; the
        points in each."""
        # every destination's outline in its source's local frame, all directed pairs at once
        hx = self.half[dst, 0] - inset * self.dx[dst]
        hy = self.half[dst, 1] - inset * self.dy[dst]
        corners = np.zeros((len(dst), 4, 3))
        corners[:, :, 0] = np.column_stack([-hx, hx, hx, -hx])
        corners[:, :, 1] = np.column_stack([-hy, -hy, hy, hy])
        Rsd = np.einsum("kji,kjl->kil", R[src], R[dst])
        loc = np.einsum("kij,kcj->kci", Rsd, corners)
        loc += np.einsum("kji,kj->ki", R[src], s[dst] - s[src])[:, None, :]
        lo = loc[:, :, :2].min(axis=1) - margin
        hi = loc[:, :, :2].max(axis=1) + margin
        if inset > 0:  # the source's own pixels as far from its border
            inner = self.half[src] - inset * np.column_stack([self.dx[src], self.dy[src]])
            lo, hi = np.maximum(lo, -inner), np.minimum(hi, inner)
        # in the source's point grid (``pitch`` apart): point (t_y, t_x) lies at
        # (t_x, t_y) * pitch - half, so the box holds t from lo / pitch + half / pitch on
        pitch = np.column_stack([self.dx[src], self.dy[src]]) * self.stride
        first = self.half[src] / pitch
        g_lo = np.maximum(np.ceil(lo / pitch + first), 0).astype(np.intp)
        g_hi = np.floor(hi / pitch + first).astype(np.intp) + 1
        g_hi = np.minimum(g_hi, np.column_stack([self.point_nx[src], self.point_ny[src]]))
        box = np.column_stack([g_lo[:, 1], g_hi[:, 1], g_lo[:, 0], g_hi[:, 0]])
        count = np.maximum(box[:, 1] - box[:, 0], 0) * np.maximum(box[:, 3] - box[:, 2], 0)
        return box, count

    def rows(self, runs: Runs, first: int = 0, last: int | None = None) -> RowBlock:
        """The rows of runs ``[first, last)`` (all by default), line by line within each."""
        last = len(runs) if last is None else last
        starts = runs.starts[first : last + 1] - runs.starts[first]
        count = np.diff(starts)
        run = np.repeat(np.arange(last - first), count)
        box = runs.box[first:last]
        width = (box[:, 3] - box[:, 2])[run]
        at = np.arange(int(starts[-1])) - starts[:-1][run]
        return RowBlock(
            src=runs.src[first:last][run],
            dst=runs.dst[first:last][run],
            row=(box[run, 0] + at // width) * self.stride,
            col=(box[run, 2] + at % width) * self.stride,
            starts=starts,
            groups=runs.groups(first, last),
        )

    def point_xyz(self, rows: RowBlock) -> FloatArray:
        """(m, 3) every row's point in its source's frame: its pixel's place and the height of
        the node on it (NaN in a hole)."""
        c = rows.src
        out = np.empty((len(c), 3))
        out[:, 0] = rows.col * self.dx[c] - self.half[c, 0]
        out[:, 1] = rows.row * self.dy[c] - self.half[c, 1]
        out[:, 2] = self.height.take(self._node(c, rows.row, rows.col))
        return out

    def _node(self, c: Ints, row: Ints, col: Ints) -> IntArray:
        """Index in :attr:`height` of the node on pixel (``row``, ``col``) of patch ``c``."""
        out: IntArray = self.origin[c] + self.nodes * (row * self.grid_nx[c] + col)
        return out
