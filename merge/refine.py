"""The default method: simultaneous GPA refinement on the full-resolution height grids.

Every patch is a continuous surface (bilinear in its own frame). For every point of a patch that
falls on another patch, the residual is its distance to that surface along the normal
(point-to-plane with the plane taken from the height map's slopes at the sub-pixel foot of the
point, so correspondences are sub-cell). All 6 rigid degrees of freedom of all patches are
solved together, every Gauss-Newton step, from one sparse normal system: this is the Generalized
Procrustes objective — the sum over every overlap point of its squared distances to the other
patches is, up to a factor, its squared distance to their mean — never a chain of pairwise
alignments.

The six unknowns of a patch are its translation (3), its rotation about z and an in-patch drift
term: a Z plane (dz/dx, dz/dy) that moves heights only. A linear Z drift during the scan is such
a plane; modelling it as a tilt of a rigid body instead would couple heights to XY (a tilt of
1 mrad shears the top of a 600 nm step 0.6 nm against its foot), and noise on steep edges would
then leak into both.

Coarse to fine: the first level works on heights smoothed by one pixel and every second point,
which widens the basin of convergence; the second on the raw heights at every point. Residuals
are re-weighted with a Cauchy function of their robust scale, so tip artefacts, dust or a changed
surface do not pull the solution.

Gauge: after every step the common motion of all patches (rotation about z, a Z plane and a
translation — none changes any residual) is removed: the mean rotation and mean drift plane are
zero, and the patch points move on average by zero from their nominal places (:mod:`merge.gauge`),
so the mosaic cannot drift away from the stage frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve

from merge.coarse import signal_information
from merge.errors import MergeCancelled
from merge.heightfield import slopes, smooth_nan
from merge.noise import estimate_noise
from merge.patchset import Patch
from merge.transforms import PatchTransform, orthonormalize, rotation_from_vector

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


STALL = 1e-4
#: Expected in-patch Z drift (metres, centre to corner) of the drift-plane prior.
DRIFT_PRIOR = 5e-9
#: Standard deviation (radians) of the prior on a patch's rotation about z.
SPIN_PRIOR = np.radians(2.0)
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
    """``T_mosaic_patch`` per patch, iterations and quality."""

    transforms: list[PatchTransform]
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
                    [
                        self.x0[c] + jj * self.dx[c] - cx,
                        self.y0[c] + ii * self.dy[c] - cy,
                        hl[ii, jj],
                    ]
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
        start of every pair's run of rows (runs are contiguous).
        """
        src_l, dst_l, idx_l, starts = [], [], [], [0]
        # Both ways: the points of each patch against the other's surface, which averages the
        # interpolation of either surface (Jacobians act on both patches of a pair).
        for a, b in pairs.tolist():
            for src, dst in ((a, b), (b, a)):
                # the destination's outline in the source's local frame
                hx, hy = self.half[dst]
                corners = np.array([[-hx, -hy, 0], [hx, -hy, 0], [hx, hy, 0], [-hx, hy, 0]])
                loc = (corners @ (R[src].T @ R[dst]).T) + R[src].T @ (s[dst] - s[src])
                lo = loc[:, :2].min(axis=0) - margin
                hi = loc[:, :2].max(axis=0) + margin
                p = self.points[self.point_start[src] : self.point_start[src + 1]]
                sel = np.flatnonzero(
                    (p[:, 0] >= lo[0])
                    & (p[:, 0] <= hi[0])
                    & (p[:, 1] >= lo[1])
                    & (p[:, 1] <= hi[1])
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
    start: Sequence[PatchTransform],
    *,
    levels: Sequence[Level] = DEFAULT_LEVELS,
    drift_prior: float = DRIFT_PRIOR,
    shift_prior: float = np.inf,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> RefineResult:
    """Refine all patch transforms at once.

    Parameters
    ----------
    patches : sequence of Patch
    pairs : (k, 2) int array
        Patch pairs that may overlap.
    start : sequence of PatchTransform
        Initial ``T_mosaic_patch`` per patch.
    levels : sequence of Level, keyword-only
        Coarse-to-fine schedule.
    drift_prior : float, keyword-only
        Expected size of the in-patch Z drift, metres from the patch centre to its corner (a
        Gaussian prior on the drift plane). Overlaps pin down the differences of neighbouring
        planes well but a mosaic-wide bend only weakly; the prior keeps that bend out.
    shift_prior : float, keyword-only
        Standard deviation (metres) of a prior holding each patch's XY near its start. It only
        matters where the data do not constrain XY (a flat overlap, the stripes of a 1-D
        grating): there the patch stays at its start instead of wandering off.
    progress : callable(iteration, residual_rms_m), keyword-only
        Called after every iteration.
    cancel : callable() -> bool, keyword-only
        Polled every iteration; true raises :class:`MergeCancelled`.
    """
    n = len(patches)
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    noise = _noise(patches, scale)
    history: list[float] = []
    iteration = 0
    converged = False
    stats: _System | None = None
    base = _Bank(patches, scale, 0.0, 1)
    state = _State.from_transforms(start, base, scale)
    start_s = state.s.copy()
    for li, level in enumerate(levels):
        bank = _Bank(patches, scale, level.smooth, level.stride)
        margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
        cand = bank.candidates(pairs, state.R, state.s, margin)
        moved = 0.0
        level_converged = False
        previous = np.inf
        for _ in range(level.max_iter):
            if cancel is not None and cancel():
                raise MergeCancelled("merge cancelled")
            if moved > 0.5 * margin:
                cand, moved = bank.candidates(pairs, state.R, state.s, margin), 0.0
            stats = _normal_system(bank, cand, state, noise)
            priors = _Priors(
                plane=state.slope * bank.radius[:, None],
                plane_sigma=drift_prior / scale,
                shift=state.s[:, :2] - (start_s[:, :2] + bank.centre[:, :2] - base.centre[:, :2]),
                shift_sigma=shift_prior / scale,
                spin=state.spin() * bank.radius,
                spin_sigma=SPIN_PRIOR * bank.radius,
            )
            delta = _solve(stats, priors)
            state.update(delta, bank.radius)
            state.fix_gauge(bank.centre, bank.point_start)
            motion = float(
                (np.abs(delta[:, :3]).max(axis=1) + np.abs(delta[:, 3:]).max(axis=1)).max(initial=0)
            )
            moved += motion
            iteration += 1
            history.append(stats.rms * scale)
            if progress is not None:
                progress(iteration, stats.rms * scale)
            # converged when no patch moves, or when the cost no longer falls (the motion left
            # is then in directions the data do not constrain, e.g. XY over a flat overlap)
            stalled = abs(previous - stats.rms) <= STALL * stats.rms
            previous = stats.rms
            if motion < level.tol or stalled:
                level_converged = True
                break
        if li == len(levels) - 1:
            converged = level_converged
    fits = _fits(stats, n, scale, noise, np.column_stack([base.dx, base.dy]))
    return RefineResult(
        transforms=state.to_transforms(base, scale),
        iterations=iteration,
        converged=converged,
        history=history,
        fits=fits,
    )


def _noise(patches: Sequence[Patch], scale: float) -> float:
    noise = float(np.nanmedian([estimate_noise(p.heights) for p in patches])) / scale
    return noise if np.isfinite(noise) and noise > 0 else 1e-3


class _State:
    """Per patch, in pixel units: ``q = R p_local + s + e_z (slope · p_local_xy)``."""

    def __init__(self, R: FloatArray, s: FloatArray, slope: FloatArray) -> None:
        self.R, self.s, self.slope = R, s, slope

    @classmethod
    def from_transforms(cls, start: Sequence[PatchTransform], bank: _Bank, scale: float) -> _State:
        n = len(start)
        R = np.array([tr.R for tr in start])
        slope = np.array([tr.slope for tr in start])
        s = np.empty((n, 3))
        for c, tr in enumerate(start):
            centre = bank.centre[c] * scale
            # the drift plane is re-centred on the patch centre (a change of its constant only)
            s[c] = (R[c] @ centre + tr.t) / scale
            s[c, 2] += float((centre[:2] - tr.centre) @ tr.slope) / scale
        return cls(R, s, slope)

    def to_transforms(self, bank: _Bank, scale: float) -> list[PatchTransform]:
        out = []
        for c in range(len(self.R)):
            centre = bank.centre[c] * scale
            t = self.s[c] * scale - self.R[c] @ centre
            out.append(PatchTransform(self.R[c], t, self.slope[c], centre[:2]))
        return out

    def spin(self) -> FloatArray:
        """Rotation angle about z of every patch, radians."""
        out: FloatArray = np.arctan2(self.R[:, 1, 0], self.R[:, 0, 0])
        return out

    def update(self, delta: FloatArray, radius: FloatArray) -> None:
        spin = np.zeros((len(delta), 3))
        spin[:, 2] = delta[:, 3] / radius
        self.R = orthonormalize(np.einsum("cij,cjk->cik", rotation_from_vector(spin), self.R))
        self.s = self.s + delta[:, :3]
        self.slope = self.slope + delta[:, 4:] / radius[:, None]

    def fix_gauge(self, centre: FloatArray, point_start: IntArray) -> None:
        """Remove the common motion (module notes): mean spin, mean plane, mean displacement."""
        weight = np.diff(point_start).astype(np.float64)
        weight = weight / weight.sum()
        pivot = weight @ self.s
        spin = np.zeros(3)
        spin[2] = -float(weight @ self.spin())
        G = rotation_from_vector(spin)
        self.R = np.einsum("ij,cjk->cik", G, self.R)
        self.s = (self.s - pivot) @ G.T + pivot
        plane = weight @ self.slope
        self.slope = self.slope - plane
        self.s[:, 2] -= (self.s[:, :2] - pivot[:2]) @ plane
        self.s = self.s - weight @ (self.s - centre)


@dataclass(frozen=True)
class _System:
    """The sparse Gauss-Newton system ``A x = g`` (6 unknowns per patch) and fit statistics."""

    rows: IntArray
    cols: IntArray
    vals: FloatArray
    g: FloatArray  # (n, 6)
    count: FloatArray  # (n,) residuals that involve the patch
    sq: FloatArray  # (n,) sum of their squared normal distances
    diag: FloatArray  # (n, 6, 6) the patch's own information block
    rms: float
    rscale: float = 0.0  # robust residual scale (pixel units)


def _normal_system(
    bank: _Bank,
    cand: tuple[IntArray, IntArray, IntArray, IntArray],
    state: _State,
    noise: float,
) -> _System:
    """The Gauss-Newton system over all correspondences, and per-patch statistics."""
    n = len(bank.centre)
    R, s, slope = state.R, state.s, state.slope
    src, dst, idx, starts = cand
    g = np.zeros((n, 6))
    count = np.zeros(n)
    sq = np.zeros(n)
    diag = np.zeros((n, 6, 6))
    empty_i = np.empty(0, dtype=np.intp)
    if len(idx) == 0:
        return _System(empty_i, empty_i, np.empty(0), g, count, sq, diag, 0.0)
    p_src = bank.points[idx]
    q = np.einsum("mij,mj->mi", R[src], p_src) + s[src]
    q[:, 2] += np.einsum("mi,mi->m", slope[src], p_src[:, :2])
    p_dst = np.einsum("mji,mj->mi", R[dst], q - s[dst])
    h, gx, gy, ok = bank.lookup(dst, p_dst)
    r = np.where(ok, p_dst[:, 2] - np.einsum("mi,mi->m", slope[dst], p_dst[:, :2]) - h, 0.0)
    # gradient of the residual with respect to q: the destination's surface normal (with its
    # drift plane), in the mosaic frame
    nrm = np.column_stack([-(gx + slope[dst, 0]), -(gy + slope[dst, 1]), np.ones_like(gx)])
    nrm = np.where(ok[:, None], nrm, 0.0)
    w_plane = np.where(ok, 1.0 / np.maximum(np.einsum("ij,ij->i", nrm, nrm), 1.0), 0.0)
    d = r * np.sqrt(w_plane)
    used = np.abs(d[ok])
    if used.size == 0:
        return _System(empty_i, empty_i, np.empty(0), g, count, sq, diag, 0.0)
    rscale = max(1.4826 * float(np.median(used)), noise)
    w = w_plane / (1.0 + (d / (3.0 * rscale)) ** 2)
    m = np.einsum("mij,mj->mi", R[dst], nrm)
    rho_s = bank.radius[src, None]
    arm = q[:, :2] - s[src, :2]
    spin = (m[:, 1] * arm[:, 0] - m[:, 0] * arm[:, 1])[:, None]
    Ja = np.concatenate([m, spin / rho_s, p_src[:, :2] / rho_s], axis=1)
    seg = starts[:-1]
    a_seg, b_seg = src[seg], dst[seg]
    # every residual informs both patches of its pair
    count += np.bincount(src[ok], minlength=n) + np.bincount(dst[ok], minlength=n)
    sq += np.bincount(src, weights=d**2, minlength=n) + np.bincount(dst, weights=d**2, minlength=n)
    Baa, ga = _segment_sums(Ja, w, r, starts)
    # Within one directed pair the destination's Jacobian is a fixed linear map of the source's,
    # Jb = -T Ja (rotations about z): its spin arm is the source's plus Δ = s_a - s_b, and its
    # plane arm (x', y') = M (x_a, y_a) + c with M = [R_b' R_a]_xy and c = [R_b' Δ]_xy.
    rho_a, rho_b = bank.radius[a_seg], bank.radius[b_seg]
    delta = s[a_seg] - s[b_seg]
    RbRa = np.einsum("kji,kjl->kil", R[b_seg], R[a_seg])
    c = np.einsum("kji,kj->ki", R[b_seg], delta)
    T = np.zeros((len(seg), 6, 6))
    T[:, [0, 1, 2], [0, 1, 2]] = 1.0
    T[:, 3, 0], T[:, 3, 1], T[:, 3, 3] = -delta[:, 1] / rho_b, delta[:, 0] / rho_b, rho_a / rho_b
    for row, k in ((4, 0), (5, 1)):
        T[:, row, 2] = c[:, k] / rho_b
        T[:, row, 4] = RbRa[:, k, 0] * rho_a / rho_b
        T[:, row, 5] = RbRa[:, k, 1] * rho_a / rho_b
    Tt = np.swapaxes(T, 1, 2)
    Bbb = T @ Baa @ Tt
    Bab = -(Baa @ Tt)
    np.add.at(g, a_seg, -ga)
    np.add.at(g, b_seg, np.einsum("kij,kj->ki", T, ga))
    np.add.at(diag, a_seg, Baa)
    np.add.at(diag, b_seg, Bbb)
    ii, jj = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")

    def triplets(
        ra: IntArray, cb: IntArray, blk: FloatArray
    ) -> tuple[IntArray, IntArray, FloatArray]:
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
    return _System(
        rows=np.concatenate([x[0] for x in parts]),
        cols=np.concatenate([x[1] for x in parts]),
        vals=np.concatenate([x[2] for x in parts]),
        g=g,
        count=count,
        sq=sq,
        diag=diag,
        rms=float(np.sqrt(np.mean(used**2))),
        rscale=rscale,
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


@dataclass(frozen=True)
class _Priors:
    """Gaussian priors on the absolute state, in the scaled units of the unknowns (pixels)."""

    plane: FloatArray  # (n, 2) drift plane times radius
    plane_sigma: float
    shift: FloatArray  # (n, 2) XY offset from the start
    shift_sigma: float
    spin: FloatArray  # (n,) rotation about z times radius
    spin_sigma: FloatArray  # (n,)


def _solve(system: _System, priors: _Priors) -> FloatArray:
    """Damped solution of the system: ``(n, 6)`` updates (translation, scaled spin and plane).

    A prior ``|value / sigma|²`` enters with the weight the data have per unit residual
    (``1 / residual scale²``), so it is a proper posterior, not a tuning knob.
    """
    n = len(system.g)
    rows, cols, vals = system.rows, system.cols, system.vals
    # Levenberg damping relative to each patch's own curvature: directions a patch's data do not
    # constrain (XY on a flat overlap) stay put instead of following noise
    on_diag = rows == cols
    dvals = np.bincount(rows[on_diag], weights=vals[on_diag], minlength=6 * n).reshape(n, 6)
    lam = np.broadcast_to(1e-4 * dvals.max(axis=1, keepdims=True) + 1e-12, (n, 6)).copy()
    g = system.g.copy()
    if system.rscale > 0:
        r2 = system.rscale**2
        for cols_, value, sigma in (
            ([4, 5], priors.plane, np.full((n, 1), priors.plane_sigma)),
            ([0, 1], priors.shift, np.full((n, 1), priors.shift_sigma)),
            ([3], priors.spin[:, None], priors.spin_sigma[:, None]),
        ):
            k = r2 / np.asarray(sigma, dtype=np.float64) ** 2
            lam[:, cols_] += k
            g[:, cols_] -= k * value
    idx = np.arange(6 * n)
    M = coo_matrix(
        (
            np.concatenate([vals, lam.ravel()]),
            (np.concatenate([rows, idx]), np.concatenate([cols, idx])),
        ),
        shape=(6 * n, 6 * n),
    ).tocsc()
    x = spsolve(M, g.ravel())
    out: FloatArray = np.asarray(x, dtype=np.float64).reshape(n, 6)
    return out


def assess(
    patches: Sequence[Patch], pairs: IntArray, transforms: Sequence[PatchTransform]
) -> list[PatchFit]:
    """Per-patch quality of given transforms on the full-resolution heights (no update).

    Used for every method, so their reports compare like with like.
    """
    scale = float(np.median([min(p.pixel_size) for p in patches]))
    bank = _Bank(patches, scale, 0.0, 1)
    state = _State.from_transforms(transforms, bank, scale)
    margin = 1.5 * float(max(bank.dx.max(), bank.dy.max()))
    cand = bank.candidates(
        np.asarray(pairs, dtype=np.intp).reshape(-1, 2), state.R, state.s, margin
    )
    system = _normal_system(bank, cand, state, _noise(patches, scale))
    pitch = np.column_stack([bank.dx, bank.dy])
    return _fits(system, len(patches), scale, _noise(patches, scale), pitch)


def _fits(
    stats: _System | None, n: int, scale: float, noise: float, pitch: FloatArray
) -> list[PatchFit]:
    """Residual RMS and translation standard deviations of every patch (metres)."""
    if stats is None:
        return [PatchFit(0, float("nan"), float("inf"), float("inf")) for _ in range(n)]
    out = []
    for c in range(n):
        k = stats.count[c]
        if k == 0:
            out.append(PatchFit(0, float("nan"), float("inf"), float("inf")))
            continue
        rms = float(np.sqrt(stats.sq[c] / k))
        info = stats.diag[c] + 1e-9 * np.trace(stats.diag[c]) * np.eye(6)
        try:
            # marginal information of the XY translation (all other unknowns free), without the
            # share that slopes of noise contribute: noise is not texture. A central difference
            # of white noise has variance σ²/2; bilinear interpolation between independent
            # differences keeps 4/9 of it on average, so (2/9) σ² per residual.
            xy_info = info[:2, :2] - info[:2, 2:] @ np.linalg.solve(info[2:, 2:], info[2:, :2])
            pitch2 = np.array([pitch[c, 0] ** -2, pitch[c, 1] ** -2])
            xy_info = signal_information(xy_info, k * noise**2 * 2.0 / 9.0 * pitch2)
            vals = np.linalg.eigvalsh(xy_info)
            xy = float(rms / np.sqrt(vals.min())) if vals.min() > 0 else float("inf")
            z = float(rms * np.sqrt(max(np.linalg.inv(info)[2, 2], 0.0)))
        except np.linalg.LinAlgError:
            xy, z = float("inf"), float("inf")
        out.append(PatchFit(int(k), rms * scale, xy * scale, z * scale))
    return out
