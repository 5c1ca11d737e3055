"""The Cramér-Rao bound of a synthetic patch set: what an efficient merge could reach (the
model behind ``crb.py``, ``merge_bench.py``'s sweep and ``merge_scale.py --bound``).

The Fisher information of all patch corrections (per patch: translation, rotation about z,
drift plane) is built from the true surface slopes at every overlap point, with the white
noise of the heights and the per-line offsets as unknowns of their own (marginalised out), each
noise sample counted once (residuals of one patch of every pair against the other). Correction
errors drawn from its inverse, applied to the true transforms and rendered like any merge,
give the map errors of an unbiased estimator that uses all the information in the data -- the
reference for what a target on the map error can ask; its registration errors are the
expectation itself (:func:`expected_registration`), not the spread of a few draws (8 draws
put the 1 µm grating's XY bound 12 % low).

The surface is not known: a residual compares two noisy scans of it, so its white noise is
twice one scan's. Counting the other scan's noise as interpolated between its pixels (4/9 of
it) took the interpolation's averaging for information, which for a surface smooth on the
pixel scale it is not (the interpolated noise moves with its neighbours): shifted by a
fraction of a pixel, a smooth random surface (correlation 2-8 px, 300 draws each) was placed by
the interpolating estimator with exact slopes within -5 to +9 % of the 2σ² bound, 11-28 % above
the 13/9σ² one.

The line offsets' system is sparse (a line meets only the lines of the patches it overlaps), so
the bound reaches mosaics of a few hundred patches (``merge_scale.py --bound``). With
``plane_prior`` the drift planes get a Gaussian prior, as the merge's have: a Bayesian bound.
Without one, a large mosaic's bend (the patch rows' relative tilts, which the line offsets leave
weakly measured) is bounded by the overlaps alone, looser than any merge that knows drift is a
few nanometres (400 folded patches of 64 x 64 px: Z 1.11 nm free, 0.51 with the simulator's
drift as the prior, and the merge 0.53 over 8 draws).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse import linalg as splinalg

from backend.synthetic import patch_set_from_synth, registration_error, scored
from hardware.sim.drift import DriftModel
from hardware.sim.surfaces import Surface
from hardware.sim.synth import SynthPatch, true_points
from merge import PatchTransform, render_mosaic
from merge.core.overlap import overlapping_pairs
from merge.core.transforms import rotation_about_z

if TYPE_CHECKING:
    pass

FloatArray = NDArray[np.float64]


def true_transforms(synth: Sequence[SynthPatch]) -> list[PatchTransform]:
    """``T_mosaic_patch`` of every synthetic patch, its in-patch drift plane included."""
    out = []
    for s in synth:
        ny, nx = s.heights.shape
        dx, dy = s.pixel_size
        slope = np.array([-s.z_drift / (dx * nx * ny), -s.z_drift / (dy * ny)])
        centre = np.array([s.origin[0], s.origin[1] + 0.5 * dy * ny])
        out.append(PatchTransform(s.rotation, s.translation, slope, centre))
    return out


def _sampled_slopes(s: SynthPatch, surface: Surface, u: FloatArray, v: FloatArray) -> FloatArray:
    """Mosaic-frame slopes that the sampled, noise-free patch ``s`` shows at fractional pixel
    ``(u, v)``: central differences of its true heights, interpolated bilinearly."""
    q = true_points(s)
    h = surface.height(q[..., 0], q[..., 1])
    gy, gx = (np.asarray(g, dtype=np.float64) for g in np.gradient(h, *s.pixel_size[::-1]))
    ny, nx = h.shape
    i0 = np.clip(np.floor(v).astype(int), 0, ny - 2)
    j0 = np.clip(np.floor(u).astype(int), 0, nx - 2)
    fv, fu = v - i0, u - j0
    out = []
    for g in (gx, gy):
        out.append(
            (1 - fv) * ((1 - fu) * g[i0, j0] + fu * g[i0, j0 + 1])
            + fv * ((1 - fu) * g[i0 + 1, j0] + fu * g[i0 + 1, j0 + 1])
        )
    local = np.column_stack(out)
    mosaic: FloatArray = local @ s.rotation[:2, :2].T  # a gradient turns with its patch
    return mosaic


def fisher_information(
    synth: Sequence[SynthPatch],
    surface: Surface,
    drift: DriftModel,
    *,
    sampled: bool = True,
    line_offsets: bool = True,
    plane_prior: tuple[float, float] | None = None,
    eps: float = 1e-10,
) -> tuple[FloatArray, FloatArray]:
    """Fisher information ``(6n, 6n)`` of the corrections (t [m], θ [rad], plane slopes) and
    the mosaic-frame rotation centre of every patch ``(n, 2)``.

    ``sampled``: the slopes a pixel grid shows (central differences of the true heights at the
    pixels), which is what any estimator working on the scans can use; else the continuous
    surface's slopes, which also count detail finer than the pixels (a looser bound).
    ``line_offsets``: the per-line noise as what it is, one unknown offset per scan line with
    a Gaussian prior, marginalised out (its information taken off by a Schur complement); else
    counted as white noise (optimistic: a line's offset then averages out along the line).
    ``plane_prior``: sigmas (x, y; metres, the plane's rise from the patch centre to its corner)
    of a Gaussian prior on every drift plane, as the merge has one (a Bayesian bound: what the
    data and that prior can give together); default none (the planes as free as the rest)."""
    n = len(synth)
    line_offsets = line_offsets and drift.line_noise > 0
    info = np.zeros((6 * n, 6 * n))
    line_start = np.cumsum([0] + [s.heights.shape[0] for s in synth])
    nl = int(line_start[-1]) if line_offsets else 0
    # unknowns x line offsets, and line offsets x line offsets: sparse (a line meets the lines
    # of the few patches it overlaps), so the bound reaches mosaics of a few hundred patches
    # both gathered as (row, column, value) triplets and summed once at the end
    cross: list[sparse.coo_matrix] = []
    lines: list[sparse.coo_matrix] = []
    q_all = [true_points(s).reshape(-1, 3) for s in synth]
    centres = np.array([q[:, :2].mean(axis=0) for q in q_all])
    tr = true_transforms(synth)
    boxes = np.array([[*q[:, :2].min(axis=0), *q[:, :2].max(axis=0)] for q in q_all])
    white = drift.noise**2 + (0.0 if line_offsets else drift.line_noise**2)
    var = 2.0 * white  # two scans of an unknown surface (the module's notes)
    for a, b in overlapping_pairs(boxes, margin=0.0).tolist():
        sb = synth[b]
        q = q_all[a]
        # nominal coordinates of a's points in patch b (its rigid truth inverted)
        pb = (q - tr[b].t) @ tr[b].R  # rows: R_b' (q - t_b)
        ny, nx = sb.heights.shape
        u = (pb[:, 0] - sb.origin[0]) / sb.pixel_size[0]
        v = (pb[:, 1] - sb.origin[1]) / sb.pixel_size[1]
        inside = (u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1)
        if not inside.any():
            continue
        q, pb = q[inside], pb[inside]
        row_a = np.repeat(np.arange(synth[a].heights.shape[0]), synth[a].heights.shape[1])[inside]
        v_in = v[inside]
        if sampled:
            hx, hy = _sampled_slopes(sb, surface, u[inside], v[inside]).T
        else:
            hx = surface.height(q[:, 0] + eps, q[:, 1]) - surface.height(q[:, 0] - eps, q[:, 1])
            hy = surface.height(q[:, 0], q[:, 1] + eps) - surface.height(q[:, 0], q[:, 1] - eps)
            hx, hy = hx / (2 * eps), hy / (2 * eps)
        m = np.column_stack([-hx, -hy, np.ones_like(hx)])
        pa = (q - tr[a].t) @ tr[a].R
        J = np.zeros((len(q), 12))
        J[:, 0:3], J[:, 6:9] = m, -m
        for k, (c, sign) in enumerate(((centres[a], 1.0), (centres[b], -1.0))):
            arm = q[:, :2] - c
            J[:, 6 * k + 3] = sign * (m[:, 1] * arm[:, 0] - m[:, 0] * arm[:, 1])
        J[:, 4:6] = pa[:, :2] - tr[a].centre
        J[:, 10:12] = -(pb[:, :2] - tr[b].centre)
        idx = np.r_[6 * a : 6 * a + 6, 6 * b : 6 * b + 6]
        info[np.ix_(idx, idx)] += J.T @ J / var
        if line_offsets:
            # the residual holds a's line offset, minus b's interpolated between two lines
            j0 = np.clip(np.floor(v_in).astype(int), 0, ny - 2)
            fv = v_in - j0
            rows = np.arange(len(q))
            L = sparse.csr_matrix(
                (
                    np.concatenate([np.ones(len(q)), -(1 - fv), -fv]),
                    (
                        np.tile(rows, 3),
                        np.concatenate(
                            [line_start[a] + row_a, line_start[b] + j0, line_start[b] + j0 + 1]
                        ),
                    ),
                ),
                shape=(len(q), nl),
            )
            JL = sparse.coo_matrix((L.T @ J).T / var)  # (12, nl)
            cross.append(sparse.coo_matrix((JL.data, (idx[JL.row], JL.col)), shape=(6 * n, nl)))
            lines.append(sparse.coo_matrix((L.T @ L) / var))
    if plane_prior is not None:
        for c, radius in enumerate(_radii(q_all)):
            for k in (0, 1):
                info[6 * c + 4 + k, 6 * c + 4 + k] += (radius / plane_prior[k]) ** 2
    if cross:
        C = _summed(cross).tocsr()
        Q = (_summed(lines) + sparse.eye(nl) / drift.line_noise**2).tocsc()
        solve = splinalg.factorized(Q)
        Ct = C.T.tocsc()
        for k in range(0, 6 * n, 240):  # the Schur complement, a block of unknowns at a time
            info[:, k : k + 240] -= C @ solve(Ct[:, k : k + 240].toarray())
    return info, centres


def _radii(points: Sequence[FloatArray]) -> FloatArray:
    """Half the diagonal (m) of every patch's measured points ``(k, 3)``: its radius."""
    return np.array([0.5 * float(np.hypot(*np.ptp(q[:, :2], axis=0))) for q in points])


def _summed(parts: Sequence[sparse.coo_matrix]) -> sparse.coo_matrix:
    """The sum of sparse matrices of one shape, built once from all their triplets (adding them
    one by one rebuilds the growing sum every time)."""
    return sparse.coo_matrix(
        (
            np.concatenate([p.data for p in parts]),
            (np.concatenate([p.row for p in parts]), np.concatenate([p.col for p in parts])),
        ),
        shape=parts[0].shape,
    )


def perturbed(
    synth: Sequence[SynthPatch], centres: FloatArray, delta: FloatArray
) -> list[PatchTransform]:
    """The true transforms moved by ``delta`` ``(n, 6)`` (t, θ about the centre, plane)."""
    out = []
    for c, tr in enumerate(true_transforms(synth)):
        G = rotation_about_z(float(delta[c, 3]))
        pivot = np.array([*centres[c], 0.0])
        t = G @ (tr.t - pivot) + pivot + delta[c, :3]
        out.append(PatchTransform(G @ tr.R, t, tr.slope + delta[c, 4:], tr.centre))
    return out


def expected_registration(
    cov: FloatArray, synth: Sequence[SynthPatch], centres: FloatArray
) -> tuple[float, float]:
    """RMS XY and Z error (metres) of every measured point after the gauge that fits them best
    (as :func:`backend.synthetic.registration_error` takes it), expected over corrections
    ``(6n,)`` with covariance ``cov`` ``(6n, 6n)`` (t, θ about ``centres``, plane): exact to
    first order in the corrections, and free of the spread of a few drawn samples.

    A patch moves its points affinely in their positions (XY: translation and spin; Z: offset
    and drift plane), and the gauge moves all points affinely too (a rigid motion in XY, an
    offset and a plane in Z). So the points' mean square after the best gauge is a quadratic
    form in the corrections, made of each patch's moments of its points' positions.
    """
    n = len(synth)
    trs = true_transforms(synth)
    count = np.array([s.heights.size for s in synth], dtype=np.float64)
    mid = count @ centres / count.sum()
    # XY, per patch (rows): translation x and y at the centre, spin times the points' RMS arm
    S, H, W = np.zeros((3 * n, 6 * n)), np.zeros((3 * n, 3)), np.repeat(count, 3)
    # Z, per patch: the moments of (1, p - plane centre, q - mid) over its points
    Sz, Hz = np.zeros((5 * n, 6 * n)), np.zeros((5 * n, 3))
    for c, s in enumerate(synth):
        q = true_points(s).reshape(-1, 3)
        arm2 = float(np.mean(np.sum((q[:, :2] - centres[c]) ** 2, axis=1)))
        off = centres[c] - mid
        S[3 * c, 6 * c], S[3 * c + 1, 6 * c + 1] = 1.0, 1.0
        S[3 * c + 2, 6 * c + 3] = np.sqrt(arm2)
        H[3 * c] = (1.0, 0.0, -off[1])
        H[3 * c + 1] = (0.0, 1.0, off[0])
        H[3 * c + 2] = (0.0, 0.0, np.sqrt(arm2))
        ny, nx = s.heights.shape
        px = np.tile(s.origin[0] + np.arange(nx) * s.pixel_size[0], ny)
        py = np.repeat(s.origin[1] + np.arange(ny) * s.pixel_size[1], nx)
        phi = np.column_stack(
            [np.ones(len(q)), px - trs[c].centre[0], py - trs[c].centre[1], q[:, :2] - mid]
        )
        w, V = np.linalg.eigh(phi.T @ phi)
        L = V * np.sqrt(np.clip(w, 0.0, None))  # moments = L L'
        E = np.zeros((5, 6 * n))
        E[0, 6 * c + 2], E[1, 6 * c + 4], E[2, 6 * c + 5] = 1.0, 1.0, 1.0
        G = np.zeros((5, 3))
        G[0, 0], G[3, 1], G[4, 2] = 1.0, 1.0, 1.0
        Sz[5 * c : 5 * c + 5], Hz[5 * c : 5 * c + 5] = L.T @ E, L.T @ G
    root = np.sqrt(W)[:, None]
    out = []
    for A, B in ((root * S, root * H), (Sz, Hz)):
        K = A - B @ np.linalg.lstsq(B, A, rcond=None)[0]  # what the best gauge leaves
        out.append(float(np.sqrt(np.einsum("ij,jk,ik->", K, cov, K) / count.sum())))
    return out[0], out[1]


def correction_scale(
    synth: Sequence[SynthPatch],
    surface: Surface,
    drift: DriftModel,
    *,
    sampled: bool = True,
    plane_prior: tuple[float, float] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """A square root ``(6n, k)`` of the bound's covariance of the corrections (times its
    transpose), and the rotation centres ``(n, 2)``: :func:`fisher_information` inverted
    outside the gauge."""
    info, centres = fisher_information(
        synth, surface, drift, sampled=sampled, plane_prior=plane_prior
    )
    # in like units (spin and drift plane times the patch radius, metres) the gauge — the common
    # motions, which no data see — is the only null space; unscaled, the plane and spin modes
    # (information ~radius² smaller) would fall under the threshold and count as error-free
    radius = _radii([true_points(s).reshape(-1, 3) for s in synth])
    D = np.ones((len(synth), 6))
    D[:, 3:] = radius[:, None]
    d = D.ravel()
    w, V = np.linalg.eigh(info / np.outer(d, d))
    keep = w > 1e-9 * w.max()
    scale: FloatArray = V[:, keep] / np.sqrt(w[keep]) / d[:, None]
    return scale, centres


def registration_bound(
    synth: Sequence[SynthPatch], surface: Surface, drift: DriftModel
) -> tuple[float, float]:
    """RMS XY and Z registration errors (nm) at the Cramér-Rao bound
    (:func:`expected_registration`)."""
    scale, centres = correction_scale(synth, surface, drift)
    xy, z = expected_registration(scale @ scale.T, synth, centres)
    return xy * 1e9, z * 1e9


def efficient_errors(
    synth: Sequence[SynthPatch],
    surface: Surface,
    drift: DriftModel,
    *,
    samples: int = 8,
    seed: int = 0,
    sampled: bool = True,
    plane_prior: tuple[float, float] | None = None,
) -> dict[str, float]:
    """Registration errors (nm, expected) and map error (nm, RMS over ``samples`` draws) at the
    Cramér-Rao bound, the floor (nm) and the spread of the map error over it."""
    from bench_cases import floor_of, map_error

    scale, centres = correction_scale(
        synth, surface, drift, sampled=sampled, plane_prior=plane_prior
    )
    xy, z = expected_registration(scale @ scale.T, synth, centres)
    patches = patch_set_from_synth(synth).patches
    floor = floor_of(list(synth), surface)
    mp = []
    for trs in _efficient_samples(synth, scale, centres, samples=samples, seed=seed):
        _, _, (G, g) = registration_error(synth, trs)
        mosaic = render_mosaic(patches, trs)
        mp.append(map_error(mosaic.heights, mosaic.origin, mosaic.pixel_size, surface, G, g))
    return {
        "reg_xy_nm": xy * 1e9,
        "reg_z_nm": z * 1e9,
        "map_nm": rms_nm(mp),
        "floor_nm": floor * 1e9,
        **spread_of(np.array(mp) / floor),
    }


def efficient_row_end(
    synth: Sequence[SynthPatch],
    surface: Surface,
    drift: DriftModel,
    *,
    samples: int = 50,
    seed: int = 0,
) -> float:
    """The worst patch at a row's end over the median patch (XY, after the gauge), as an
    efficient merge would make it: the median over ``samples`` draws of the bound's errors.

    A patch at a row's end has fewer neighbours to hold it, and the worst of ten is set beside
    the median of all: even at the bound the statistic is about 3 on the paper grid (the
    tip-drawn sweep's 20 nm cases, 100 samples: median 3.0-3.1, 90th percentile 4.7).
    """
    scale, centres = correction_scale(synth, surface, drift)
    cols = np.array([s.col for s in synth])
    ends = (cols == cols.min()) | (cols == cols.max())  # the snake's rows end there
    stats = []
    for trs in _efficient_samples(synth, scale, centres, samples=samples, seed=seed):
        off = np.hypot(*scored(list(synth), trs).patches[:, :2].T)
        stats.append(off[ends].max() / max(float(np.median(off)), 1e-15))
    return float(np.median(stats))


def _efficient_samples(
    synth: Sequence[SynthPatch],
    scale: FloatArray,
    centres: FloatArray,
    *,
    samples: int,
    seed: int,
) -> Iterator[list[PatchTransform]]:
    """``samples`` draws of the transforms an efficient merge would return: the truth moved by
    the bound's errors (``scale`` from :func:`correction_scale`, its columns' covariance)."""
    rng = np.random.default_rng(seed)
    for _ in range(samples):
        delta = (scale @ rng.standard_normal(scale.shape[1])).reshape(-1, 6)
        yield perturbed(synth, centres, delta)


def spread_of(ratio: FloatArray) -> dict[str, float]:
    """Median, 90th percentile and largest of map errors over the floor."""
    return {
        "map_over_floor_median": float(np.median(ratio)),
        "map_over_floor_p90": float(np.percentile(ratio, 90)),
        "map_over_floor_max": float(ratio.max()),
    }


def rms_nm(values: Sequence[float]) -> float:
    """RMS of ``values`` (metres), nm."""
    return float(np.sqrt(np.mean(np.square(values))) * 1e9)
