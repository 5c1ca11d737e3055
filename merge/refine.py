"""The default method: simultaneous GPA refinement on the full-resolution height grids.

Every patch is a continuous surface (bilinear in its own frame). For every point of a patch that
falls on another patch, the residual is its distance to that surface along the normal
(point-to-plane with the plane taken from the height map's slopes at the sub-pixel foot of the
point, so correspondences are sub-cell). All 6 rigid degrees of freedom of all patches are
solved together, every Gauss-Newton step, from one sparse normal system: this is the Generalized
Procrustes objective — the sum over every overlap point of its squared distances to the other
patches is, up to a factor, its squared distance to their mean — never a chain of pairwise
alignments. The rotations include the two tilts, which absorb a linear Z drift inside a patch.

Coarse to fine: the first level works on heights smoothed by one pixel and every second point,
which widens the basin of convergence; the second on the raw heights at every point. Residuals
are re-weighted with a Cauchy function of their robust scale, so tip artefacts, dust or a changed
surface do not pull the solution.

Gauge: after every step, the one rigid motion that best brings the mosaic back onto the nominal
placement (over all patch points) is applied to every patch, so the mosaic cannot drift away from
the stage frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve

from merge.errors import MergeCancelled
from merge.heightfield import slopes, smooth_nan
from merge.gauge import anchor_to_nominal, nominal_points
from merge.noise import estimate_noise
from merge.patchset import Patch
from merge.transforms import orthonormalize, rotation_from_vector

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
Progress = Callable[[int, float], None]


@dataclass(frozen=True)
class Level:
    """One stage of the coarse-to-fine schedule: smoothing (pixels) and point stride."""

    smooth: float
    stride: int
    max_iter: int
    tol: float  # largest patch motion (pixels) that counts as converged


DEFAULT_LEVELS = (Level(smooth=1.0, stride=2, max_iter=10, tol=0.05), Level(0.0, 1, 30, 1e-3))


@dataclass(frozen=True)
class PatchFit:
    """Per-patch quality after the refinement (metres, counts)."""

    correspondences: int
    residual_rms: float
    xy_sigma: float
    z_sigma: float


@dataclass(frozen=True)
class RefineResult:
    """Transforms ``q = R p + t`` (nominal patch point to mosaic), iterations and quality."""

    R: FloatArray
    t: FloatArray
    iterations: int
    converged: bool
    history: list[float]
    fits: list[PatchFit]


class _Bank:
    """All patches of one level, flattened for vectorized look-ups (lengths in pixel units)."""

    def __init__(self, patches: Sequence[Patch], scale: float, smooth: float, stride: int) -> None:
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
        h_flat, gx_flat, gy_flat, pts, owner = [], [], [], [], []
        self.offset = np.zeros(n, dtype=np.intp)
        self.point_start = np.zeros(n + 1, dtype=np.intp)
        total = 0
        for c, p in enumerate(patches):
            h = p.heights / scale
            if smooth > 0:
                h = smooth_nan(h, smooth)
            ny, nx = h.shape
            w, hh = (nx - 1) * self.dx[c], (ny - 1) * self.dy[c]
            cx, cy = self.x0[c] + 0.5 * w, self.y0[c] + 0.5 * hh
            self.centre[c] = (cx, cy, float(np.nanmedian(h)))
            self.half[c] = (0.5 * w, 0.5 * hh)
            self.radius[c] = float(np.hypot(0.5 * w, 0.5 * hh))
            hl = h - self.centre[c, 2]
            gx, gy = slopes(h, (self.dx[c], self.dy[c]))
            self.offset[c] = total
            total += h.size
            h_flat.append(hl.ravel())
            gx_flat.append(gx.ravel())
            gy_flat.append(gy.ravel())
            ii, jj = np.meshgrid(np.arange(0, ny, stride), np.arange(0, nx, stride), indexing="ij")
            keep = np.isfinite(h[ii, jj])
            ii, jj = ii[keep], jj[keep]
            pts.append(
                np.column_stack(
                    [self.x0[c] + jj * self.dx[c] - cx, self.y0[c] + ii * self.dy[c] - cy, hl[ii, jj]]
                )
            )
            owner.append(np.full(len(ii), c, dtype=np.intp))
            self.point_start[c + 1] = self.point_start[c] + len(ii)
        self.h = np.concatenate(h_flat)
        self.gx = np.concatenate(gx_flat)
        self.gy = np.concatenate(gy_flat)
        self.points = np.concatenate(pts)

    def lookup(
        self, dst: IntArray, p_local: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Height (local), slopes and validity of patch ``dst[i]`` under local point ``i``."""
        nx, ny = self.nx[dst], self.ny[dst]
        u = (p_local[:, 0] + self.half[dst, 0]) / self.dx[dst]
        v = (p_local[:, 1] + self.half[dst, 1]) / self.dy[dst]
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        i0 = np.clip(np.floor(v).astype(np.intp), 0, ny - 2)
        j0 = np.clip(np.floor(u).astype(np.intp), 0, nx - 2)
        fv, fu = np.clip(v - i0, 0.0, 1.0), np.clip(u - j0, 0.0, 1.0)
        k = self.offset[dst] + i0 * nx + j0
        w00, w01, w10, w11 = (1 - fv) * (1 - fu), (1 - fv) * fu, fv * (1 - fu), fv * fu
        out = []
        ok = inside
        for a in (self.h, self.gx, self.gy):
            val = w00 * a[k] + w01 * a[k + 1] + w10 * a[k + nx] + w11 * a[k + nx + 1]
            ok = ok & np.isfinite(val)
            out.append(val)
        return out[0], out[1], out[2], ok

    def candidates(
        self, pairs: IntArray, R: FloatArray, s: FloatArray, margin: float
    ) -> tuple[IntArray, IntArray, IntArray, IntArray]:
        """Points of every source patch that may fall on every destination patch.

        Returns per row the source patch, destination patch and global point index, plus the
        start of every directed pair's run of rows (runs are contiguous).
        """
        src_l, dst_l, idx_l, starts = [], [], [], [0]
        for a, b in pairs:
            for src, dst in ((a, b), (b, a)):
                # the destination's outline in the source's local frame
                hx, hy = self.half[dst]
                corners = np.array([[-hx, -hy, 0], [hx, -hy, 0], [hx, hy, 0], [-hx, hy, 0]])
                loc = (corners @ (R[src].T @ R[dst]).T) + R[src].T @ (s[dst] - s[src])
                lo = loc[:, :2].min(axis=0) - margin
                hi = loc[:, :2].max(axis=0) + margin
                p = self.points[self.point_start[src] : self.point_start[src + 1]]
                sel = np.flatnonzero(
                    (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1])
                )
                if len(sel) == 0:
                    continue
                src_l.append(np.full(len(sel), src, dtype=np.intp))
                dst_l.append(np.full(len(sel), dst, dtype=np.intp))
                idx_l.append(sel + self.point_start[src])
                starts.append(starts[-1] + len(sel))
        if not idx_l:
            e = np.empty(0, dtype=np.intp)
            return e, e, e, np.zeros(1, dtype=np.intp)
        return (
            np.concatenate(src_l),
            np.concatenate(dst_l),
            np.concatenate(idx_l),
            np.array(starts, dtype=np.intp),
        )


def refine(
    patches: Sequence[Patch],
    pairs: IntArray,
    R0: FloatArray,
    t0: FloatArray,
    *,
    levels: Sequence[Level] = DEFAULT_LEVELS,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> RefineResult:
    """Refine all patch transforms at once.

    Parameters
    ----------
    patches : sequence of Patch
    pairs : (k, 2) int array
        Patch pairs that may overlap.
    R0, t0 : (n, 3, 3), (n, 3) arrays
        Initial ``T_mosaic_patch`` (metres).
    levels : sequence of Level, keyword-only
        Coarse-to-fine schedule.
    progress : callable(iteration, residual_rms_m), keyword-only
        Called after every iteration.
    cancel : callable() -> bool, keyword-only
        Polled every iteration; true raises :class:`MergeCancelled`.
    """
    n = len(patches)
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    noise = float(np.nanmedian([estimate_noise(p.heights) for p in patches])) / scale
    noise = noise if np.isfinite(noise) and noise > 0 else 1e-3
    R = np.array(R0, dtype=np.float64, copy=True)
    t = np.array(t0, dtype=np.float64, copy=True) / scale
    history: list[float] = []
    iteration = 0
    converged = False
    stats: _System | None = None
    # the nominal placement of every patch, for the gauge: local points + centre
    nominal, owner = nominal_points(patches)
    nominal = nominal / scale
    for li, level in enumerate(levels):
        bank = _Bank(patches, scale, level.smooth, level.stride)
        margin = 3.0 * float(max(bank.dx.max(), bank.dy.max()))
        # state per patch: q = R_c p_local + s_c
        s = np.einsum("cij,cj->ci", R, bank.centre) + t
        cand = bank.candidates(pairs, R, s, margin)
        moved = 0.0
        level_converged = False
        previous = np.inf
        for _ in range(level.max_iter):
            if cancel is not None and cancel():
                raise MergeCancelled("merge cancelled")
            if moved > 0.5 * margin:
                cand, moved = bank.candidates(pairs, R, s, margin), 0.0
            stats = _normal_system(bank, cand, R, s, noise)
            delta = _solve(stats)
            dw = delta[:, 3:] / bank.radius[:, None]
            R = orthonormalize(np.einsum("cij,cjk->cik", rotation_from_vector(dw), R))
            s = s + delta[:, :3]
            motion = float(
                (np.abs(delta[:, :3]).max(axis=1) + np.abs(delta[:, 3:]).max(axis=1)).max(initial=0)
            )
            moved += motion
            t = s - np.einsum("cij,cj->ci", R, bank.centre)
            R, t = anchor_to_nominal(nominal, owner, R, t)
            s = np.einsum("cij,cj->ci", R, bank.centre) + t
            iteration += 1
            history.append(stats.rms * scale)
            if progress is not None:
                progress(iteration, stats.rms * scale)
            # converged when no patch moves, or when the cost no longer falls (the motion left
            # is then in directions the data do not constrain, e.g. XY over a flat overlap)
            stalled = abs(previous - stats.rms) <= 1e-4 * stats.rms
            previous = stats.rms
            if motion < level.tol or stalled:
                level_converged = True
                break
        if li == len(levels) - 1:
            converged = level_converged
    fits = _fits(stats, n, scale)
    return RefineResult(
        R=R, t=t * scale, iterations=iteration, converged=converged, history=history, fits=fits
    )


@dataclass(frozen=True)
class _System:
    """The sparse Gauss-Newton system ``A x = g`` (6 unknowns per patch) and fit statistics."""

    rows: IntArray
    cols: IntArray
    vals: FloatArray
    g: FloatArray  # (n, 6)
    count: FloatArray  # (n,) residuals where the patch is the source
    sq: FloatArray  # (n,) sum of squared normal distances of those
    diag: FloatArray  # (n, 6, 6) the patch's own information block
    rms: float


def _normal_system(
    bank: _Bank,
    cand: tuple[IntArray, IntArray, IntArray, IntArray],
    R: FloatArray,
    s: FloatArray,
    noise: float,
) -> _System:
    """The Gauss-Newton system over all correspondences, and per-patch statistics."""
    n = len(bank.centre)
    src, dst, idx, starts = cand
    g = np.zeros((n, 6))
    count = np.zeros(n)
    sq = np.zeros(n)
    diag = np.zeros((n, 6, 6))
    empty_i = np.empty(0, dtype=np.intp)
    if len(idx) == 0:
        return _System(empty_i, empty_i, np.empty(0), g, count, sq, diag, 0.0)
    q = np.einsum("mij,mj->mi", R[src], bank.points[idx]) + s[src]
    p_dst = np.einsum("mji,mj->mi", R[dst], q - s[dst])
    h, gx, gy, ok = bank.lookup(dst, p_dst)
    r = np.where(ok, p_dst[:, 2] - h, 0.0)
    nrm = np.column_stack([-gx, -gy, np.ones_like(gx)])
    w_plane = np.where(ok, 1.0 / np.einsum("ij,ij->i", nrm, nrm), 0.0)
    d = r * np.sqrt(w_plane)
    used = np.abs(d[ok])
    if used.size == 0:
        return _System(empty_i, empty_i, np.empty(0), g, count, sq, diag, 0.0)
    rscale = max(1.4826 * float(np.median(used)), noise)
    w = w_plane / (1.0 + (d / (3.0 * rscale)) ** 2)
    m = np.einsum("mij,mj->mi", R[dst], np.where(ok[:, None], nrm, 0.0))
    Ja = np.concatenate([m, np.cross(q - s[src], m) / bank.radius[src, None]], axis=1)
    seg = starts[:-1]
    a_seg, b_seg = src[seg], dst[seg]
    count += np.bincount(src[ok], minlength=n)
    sq += np.bincount(src, weights=d**2, minlength=n)
    Baa, ga = _segment_sums(Ja, w, r, starts)
    # Within one directed pair the destination's Jacobian is a fixed linear map of the source's:
    # (q - s_b) x m = (q - s_a) x m + (s_a - s_b) x m, so Jb = -T Ja with
    # T = [[I, 0], [K, α I]], α = ρa / ρb and K the cross-product matrix of (s_a - s_b) / ρb.
    alpha = bank.radius[a_seg] / bank.radius[b_seg]
    beta = (s[a_seg] - s[b_seg]) / bank.radius[b_seg, None]
    T = np.zeros((len(seg), 6, 6))
    T[:, [0, 1, 2], [0, 1, 2]] = 1.0
    T[:, [3, 4, 5], [3, 4, 5]] = alpha[:, None]
    T[:, 3, 1], T[:, 3, 2] = -beta[:, 2], beta[:, 1]
    T[:, 4, 0], T[:, 4, 2] = beta[:, 2], -beta[:, 0]
    T[:, 5, 0], T[:, 5, 1] = -beta[:, 1], beta[:, 0]
    Tt = np.swapaxes(T, 1, 2)
    Bbb = T @ Baa @ Tt
    Bab = -(Baa @ Tt)
    np.add.at(g, a_seg, -ga)
    np.add.at(g, b_seg, np.einsum("kij,kj->ki", T, ga))
    np.add.at(diag, a_seg, Baa)
    ii, jj = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")

    def triplets(ra: IntArray, cb: IntArray, blk: FloatArray) -> tuple[IntArray, ...]:
        return (
            (ra[:, None, None] * 6 + ii).ravel(),
            (cb[:, None, None] * 6 + jj).ravel(),
            blk.ravel(),
        )

    parts = [
        triplets(a_seg, a_seg, Baa),
        triplets(b_seg, b_seg, Bbb),
        triplets(a_seg, b_seg, Bab),
        triplets(b_seg, a_seg, np.swapaxes(Bab, 1, 2)),
    ]
    rows = [x[0] for x in parts]
    cols = [x[1] for x in parts]
    vals = [x[2] for x in parts]
    return _System(
        rows=np.concatenate(rows),
        cols=np.concatenate(cols),
        vals=np.concatenate(vals),
        g=g,
        count=count,
        sq=sq,
        diag=diag,
        rms=float(np.sqrt(np.mean(used**2))),
    )


_IU = np.triu_indices(6)


def _segment_sums(
    J: FloatArray, w: FloatArray, r: FloatArray, starts: IntArray
) -> tuple[FloatArray, FloatArray]:
    """Per run of rows: ``Σ w J J'`` (k, 6, 6) and ``Σ w r J`` (k, 6).

    Only the 21 distinct products of the symmetric outer product are formed, in chunks of whole
    runs so memory stays bounded.
    """
    k = len(starts) - 1
    upper = np.zeros((k, 21))
    wJ = J * w[:, None]
    grad = np.add.reduceat(wJ * r[:, None], starts[:-1], axis=0)
    budget = 400_000
    first = 0
    while first < k:
        last = int(np.searchsorted(starts, starts[first] + budget, side="right")) - 1
        last = min(max(last, first + 1), k)
        lo, hi = starts[first], starts[last]
        prod = wJ[lo:hi, _IU[0]] * J[lo:hi, _IU[1]]
        upper[first:last] = np.add.reduceat(prod, starts[first:last] - lo, axis=0)
        first = last
    B = np.zeros((k, 6, 6))
    B[:, _IU[0], _IU[1]] = upper
    B[:, _IU[1], _IU[0]] = upper
    return B, grad


def _solve(system: _System) -> FloatArray:
    """Damped solution of the system: ``(n, 6)`` updates (translation, scaled rotation)."""
    n = len(system.g)
    rows, cols, vals = system.rows, system.cols, system.vals
    # Levenberg damping relative to each patch's own curvature: directions a patch's data do not
    # constrain (XY on a flat overlap) stay put instead of following noise
    on_diag = rows == cols
    dvals = np.bincount(rows[on_diag], weights=vals[on_diag], minlength=6 * n).reshape(n, 6)
    lam = 1e-4 * dvals.max(axis=1, keepdims=True) + 1e-12
    damp = np.broadcast_to(lam, (n, 6)).ravel()
    idx = np.arange(6 * n)
    M = coo_matrix(
        (np.concatenate([vals, damp]), (np.concatenate([rows, idx]), np.concatenate([cols, idx]))),
        shape=(6 * n, 6 * n),
    ).tocsc()
    x = spsolve(M, system.g.ravel())
    out: FloatArray = np.asarray(x, dtype=np.float64).reshape(n, 6)
    return out


def assess(
    patches: Sequence[Patch], pairs: IntArray, R: FloatArray, t: FloatArray
) -> list[PatchFit]:
    """Per-patch quality of given transforms on the full-resolution heights (no update).

    Used for every method, so their reports compare like with like.
    """
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    noise = float(np.nanmedian([estimate_noise(p.heights) for p in patches])) / scale
    noise = noise if np.isfinite(noise) and noise > 0 else 1e-3
    bank = _Bank(patches, scale, 0.0, 1)
    s = np.einsum("cij,cj->ci", R, bank.centre) + np.asarray(t) / scale
    margin = 3.0 * float(max(bank.dx.max(), bank.dy.max()))
    cand = bank.candidates(np.asarray(pairs, dtype=np.intp).reshape(-1, 2), R, s, margin)
    return _fits(_normal_system(bank, cand, R, s, noise), len(patches), scale)


def _fits(stats: _System | None, n: int, scale: float) -> list[PatchFit]:
    if stats is None:
        return [PatchFit(0, float("nan"), float("inf"), float("inf")) for _ in range(n)]
    count, sq, diag = stats.count, stats.sq, stats.diag
    out = []
    for c in range(n):
        if count[c] == 0:
            out.append(PatchFit(0, float("nan"), float("inf"), float("inf")))
            continue
        rms = float(np.sqrt(sq[c] / count[c]))
        info = diag[c][:3, :3]
        # marginal standard deviations of the translation with the rotations free
        try:
            cov = np.linalg.inv(diag[c] + 1e-12 * np.eye(6))[:3, :3] * rms**2
            xy = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
            z = float(np.sqrt(max(cov[2, 2], 0.0)))
        except np.linalg.LinAlgError:
            xy, z = float("inf"), float("inf")
        if info[0, 0] + info[1, 1] == 0:
            xy = float("inf")
        out.append(PatchFit(int(count[c]), rms * scale, xy * scale, z * scale))
    return out
