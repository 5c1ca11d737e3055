"""How well the fit places every patch: standard deviations marginal over the whole mosaic.

A patch's own information block says how well it is held *if every other patch stood still*.
That is the local question (do its overlaps constrain XY at all?), but not the placement
uncertainty: a block of patches tied to the rest by overlaps with little texture (a grating's
flat faces, say) can move together, every patch in it well held by its neighbours, and a
report built from the own blocks would claim tenths of a nanometre for a block that is off by
several. The marginal covariance — every other unknown free, the gauge (the common motion of
every group of patches the overlaps tie together, which no data see) fixed — counts such
collective modes. A patch that overlaps nothing is its own group, held whole.

It is the top-left block of the inverse of the bordered matrix ``[[A, G], [G', 0]]``, with ``A`` the
information of all unknowns and ``G`` the common motions; one sparse LU serves the columns of every
patch's translation. Two corrections keep the residuals' information honest: the share that slopes
of the noise claim is taken out (:func:`merge.core.information.noise_share`: noise is not texture),
and Z variances are scaled by how much the residuals of one scan line move together
(:func:`merge.core.information.line_design`: per-line offsets do not average out like white noise).
The drift planes' prior the refinement solved with is counted as its steps counted it: the
uncertainty is the posterior's, not the data's alone (:func:`translation_sigmas`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import qr
from scipy.sparse import bmat, coo_matrix, csc_matrix

from merge.core.overlap import overlap_groups
from merge.core.progress import checkpoint
from merge.core.selected_inverse import diagonal_blocks, slabs
from merge.core.sparse import factor_symmetric

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Ridge on ``A``, relative to its largest diagonal entry: keeps directions no data see finite.
RIDGE = 1e-9
#: A variance above this fraction of the ridge's own (``1 / ridge``) is a direction no data see.
UNSEEN = 1e-3
#: Information (relative to ``A``'s largest diagonal entry) that holds a translation no data see.
PIN = 1e6
#: Information (relative to ``A``'s largest diagonal entry) that holds the patch fixing the gauge
#: of the slab by slab solution (:func:`_translation_blocks`): its leak is the inverse.
GAUGE_HOLD = 1e10
#: Curvature along a gauge mode (relative to ``A``'s largest diagonal entry, per unit length of
#: the mode) from which a prior sees it: a thousand times the ridge's in the slab by slab
#: solution (1e-12), above what the linearisation leaves along a common spin (1e-11); the
#: drift planes' prior tilts the heights at 1e-6-4e-5 along x and 4e-8-1e-6 along y (400
#: patches of 256 and 64 px).
SEEN_MODE = 1e-9
#: Rounds of holding translations no data see.
PASSES = 4
#: Of the variances above the unseen level, those above this fraction of the largest are the
#: unseen translations themselves; the rest are shares the gauge spread from them.
SHARE = 0.25
#: Systems up to this many unknowns are solved dense: the marginal covariances need as many
#: right-hand sides as translations (half the unknowns), and LAPACK solves them as one
#: matrix-matrix problem. Its memory and time grow as the square and cube of the size (400
#: patches: 0.47 s, and 150 MB, the whole merge's peak), and so did a sparse LU's one column at
#: a time (1,600 patches: 22 s), so larger systems get only the diagonal blocks, slab by slab
#: (:mod:`merge.core.selected_inverse`: 400 patches in 0.3 s, 1,600 in 1.2 s). From 100 patches
#: on the slabs are faster too (12 ms against 22, the sigmas within 5e-5 of the dense ones) and
#: the dense matrices were the report's peak there (10 MB, 25 bytes per input pixel).
DENSE_MAX = 300


def tied_groups(rows: IntArray, cols: IntArray, n: int) -> IntArray:
    """Label (n,) of every patch: which group of patches the information ties together.

    ``rows, cols``: the nonzero entries of the information matrix (6 unknowns per patch).
    Patches that overlap no other (and groups that overlap no other group) have common
    motions of their own that no data see: each group needs a gauge of its own.
    """
    return overlap_groups(_unit_pairs(rows, cols, n), n)


def gauge_modes(
    s: FloatArray, radius: FloatArray, weight: FloatArray, groups: IntArray | None = None
) -> FloatArray:
    """The common motions of every group of patches, ``(6 n, 6 g)``, in the unknowns of the
    refinement (``g`` groups of two patches or more; all patches one group by default).

    Per group: translation x, y, z; a spin about z and a Z plane (a tilt of the heights), both
    about the weighted centre of its patches. ``s`` (n, 3) patch positions, ``radius`` (n,) the
    scale of each patch's spin and plane unknowns, ``weight`` (n,) the pivot's weights (pixel
    units), ``groups`` (n,) labels from :func:`tied_groups`. A patch alone in its group has no
    mode: nothing ties it, and :func:`translation_covariances` holds all its unknowns.
    """
    n = len(s)
    groups = np.zeros(n, dtype=np.intp) if groups is None else np.asarray(groups)
    columns = []
    for label in np.unique(groups):
        member = groups == label
        if member.sum() < 2:
            continue
        w = weight[member]
        pivot = (w / w.sum()) @ s[member, :2]
        dx, dy = s[:, 0] - pivot[0], s[:, 1] - pivot[1]
        G = np.zeros((n, 6, 6))
        G[:, 0, 0] = G[:, 1, 1] = G[:, 2, 2] = 1.0
        G[:, 0, 3], G[:, 1, 3], G[:, 3, 3] = -dy, dx, radius  # spin
        G[:, 2, 4], G[:, 4, 4] = dx, radius  # plane along x
        G[:, 2, 5], G[:, 5, 5] = dy, radius  # plane along y
        G[~member] = 0.0
        columns.append(G.reshape(6 * n, 6))
    out: FloatArray = np.hstack(columns) if columns else np.zeros((6 * n, 0))
    # like units: each mode scaled to unit length
    norms: FloatArray = np.linalg.norm(out, axis=0)
    return out / np.where(norms > 0, norms, 1.0)


def translation_covariances(
    rows: IntArray,
    cols: IntArray,
    vals: FloatArray,
    gauge: FloatArray,
    *,
    positions: FloatArray | None = None,
    prior: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Marginal covariances of every patch's translation, in units of the residual variance.

    Parameters
    ----------
    rows, cols, vals : arrays
        Triplets of the information matrix ``A`` (6 n x 6 n), duplicates summed.
    gauge : (6 n, g) array
        The common motions (:func:`gauge_modes`), held fixed.
    positions : (n, 2) array, keyword-only
        Where the patches lie (any unit): large systems are cut into slabs along the longer
        axis of the mosaic (:mod:`merge.core.selected_inverse`); default an order from the
        links alone.
    prior : (6 n,) array, keyword-only
        Information of Gaussian priors on single unknowns, added to ``A``'s diagonal (in
        ``A``'s units); default none.

    Returns
    -------
    xy : (n, 2, 2) array
        Covariance of each patch's XY translation (``inf`` on its diagonal where no data see it).
    z : (n,) array
        Variance of each patch's Z translation (``inf`` likewise).
    """
    size = gauge.shape[0]
    n = size // 6
    A = coo_matrix((vals, (rows, cols)), shape=(size, size)).tocsc()
    checkpoint()  # each of these takes tenths of a second on 10,000 patches
    top = max(float(A.diagonal().max(initial=0.0)), 1e-300)
    ridge = RIDGE * top
    unseen = UNSEEN / ridge
    parts = None if size <= DENSE_MAX else _slabs_of(rows, cols, n, positions)
    checkpoint()
    # a patch tied to no other (no gauge mode moves it) is held whole, spin and plane too: left
    # free, they would take up a share of the gauge (a mean spin of zero) from the others
    alone = np.asarray(~np.abs(gauge).reshape(n, 6, -1).any(axis=(1, 2)), dtype=bool)
    held = np.repeat(alone[:, None], 3, axis=1)
    # A translation no data see has a variance of about 1 / ridge, and the gauge (the mean
    # motion is zero) would spread a share of it over every other patch: such translations
    # are held and solved again, until no new one appears (a block that floats as a whole
    # shows up only once its members' shares are gone).
    for _ in range(PASSES):
        pin = np.zeros((n, 6))
        pin[:, :3] = np.where(held, PIN * top, 0.0)
        pin[alone, 3:] = PIN * top
        # held in its gauge, the slab by slab solution needs no ridge for its conditioning, and
        # the ridge's bias grows with the distance from the patch held (400 patches: Z sigmas
        # up to 1.1 % off the dense solution's; with a thousandth of it, 0.03 %)
        slack = ridge if parts is None else 1e-3 * ridge
        B = A + _diagonal(slack + pin.ravel() + (0.0 if prior is None else prior))
        block = _translation_blocks(B, gauge, parts, stiff=PIN * top)
        var = np.column_stack(
            [np.repeat(np.linalg.eigvalsh(block[:, :2, :2])[:, 1:], 2, axis=1), block[:, 2, 2]]
        )
        lost = (var > unseen) & ~held
        if not lost.any():
            break
        # the unseen themselves, not the shares the gauge spread from them
        held |= lost & (var >= SHARE * var[lost].max())
    xy: FloatArray = block[:, :2, :2].copy()
    z: FloatArray = block[:, 2, 2].copy()
    xy[held[:, :2].any(axis=1)] = np.diag([np.inf, np.inf])
    z[held[:, 2]] = np.inf
    return xy, z


def _slabs_of(
    rows: IntArray, cols: IntArray, n: int, positions: FloatArray | None
) -> list[IntArray]:
    """The slabs of the selected inversion: the patches in order along the mosaic's longer
    axis (or by their links alone)."""
    order = None
    if positions is not None:
        along = int(np.argmax(np.ptp(positions, axis=0)))
        order = np.lexsort((positions[:, 1 - along], positions[:, along])).astype(np.intp)
    return slabs(_unit_pairs(rows, cols, n), n, order)


def _translation_blocks(
    B: csc_matrix, gauge: FloatArray, parts: list[IntArray] | None, *, stiff: float
) -> FloatArray:
    """The (n, 3, 3) translation blocks of the top-left block of ``[[B, G], [G', 0]]⁻¹``.

    Dense (one LAPACK solve for every translation's column) without ``parts``. Else slab by
    slab (:func:`merge.core.selected_inverse.diagonal_blocks`) in another gauge, which keeps
    the matrix well conditioned: one patch of every group held (``stiff``) in as many of its
    unknowns as the group has modes, ``C = (B + holds)⁻¹``. The mean-zero gauge's estimate is
    the held one's moved along the modes, ``x = Π y`` with ``Π = I - G (G'G)⁻¹ G'``, so the
    blocks are those of ``Π C Π'``: ``C`` less ``G K (CG)' + (CG) K G'`` plus
    ``G K (G'CG) K G'`` (``K = (G'G)⁻¹``, one sparse LU for ``CG``, as many columns as modes).
    The bordered form itself would subtract two numbers of the size of ``1 / ridge``. Moving
    along a mode leaves the cost unchanged only where ``B`` does not see it; the modes a prior
    gives a cost (the drift planes' prior, along the common tilts of the heights) are not held
    but conditioned on after (:data:`SEEN_MODE`): held, 400 patches of 256 x 256 px had Z
    sigmas up to 18 % (median 6 %) below the bordered inverse's; conditioned on, within 0.2 %.
    """
    size = B.shape[0]
    n = size // 6
    if parts is None:
        K = bmat([[B, csc_matrix(gauge)], [csc_matrix(gauge.T), None]], format="csc")
        picks = (6 * np.arange(n)[:, None] + np.arange(3)).ravel()
        rhs = np.zeros((K.shape[0], len(picks)))
        rhs[picks, np.arange(len(picks))] = 1.0
        X = np.linalg.solve(K.toarray(), rhs)[:size]
        dense: FloatArray = X[picks].reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]
        return dense
    if not gauge.shape[1]:
        no_modes: FloatArray = diagonal_blocks(B, 6, parts)[:, :3, :3]
        return no_modes
    # unknowns held (the caller's pins: translations no data see) move with no mode, which
    # leaves the cost unchanged only without them
    gauge = np.where((B.diagonal() >= stiff)[:, None], 0.0, gauge)
    # the modes a prior sees (the drift planes' prior tilts the heights at a cost) are not free
    # to move along: they are conditioned on afterwards
    seen = _seen_modes(B, gauge)
    free, tied = gauge[:, ~seen], gauge[:, seen]
    held = B + _diagonal(GAUGE_HOLD / PIN * stiff * _gauge_holds(free))
    C = diagonal_blocks(held, 6, parts)
    lu = factor_symmetric(held)
    Kg = np.linalg.pinv(free.T @ free, hermitian=True)

    def project(X: FloatArray) -> FloatArray:
        """``Π X`` with ``Π = I - G K G'`` of the free modes."""
        out: FloatArray = X - free @ (Kg @ (free.T @ X))
        return out

    CG = np.asarray(lu.solve(np.ascontiguousarray(free)))
    mid = Kg @ (free.T @ CG) @ Kg
    Gt = free.reshape(n, 6, -1)[:, :3, :]
    Ct = CG.reshape(n, 6, -1)[:, :3, :]
    cross = np.einsum("nig,gh,njh->nij", Gt, Kg, Ct)
    out: FloatArray = (
        C[:, :3, :3] - cross - np.swapaxes(cross, 1, 2) + np.einsum("nig,gh,njh->nij", Gt, mid, Gt)
    )
    if tied.shape[1]:
        # Σ0 = Π C Π' holds the free modes at zero; holding the seen ones too conditions it on
        # G1'x = 0: Σ = Σ0 - Σ0 G1 (G1' Σ0 G1)⁻¹ G1' Σ0 (one solve, a column per mode)
        SG = project(np.asarray(lu.solve(np.ascontiguousarray(project(tied)))))
        St = SG.reshape(n, 6, -1)[:, :3, :]
        inner = np.linalg.pinv(tied.T @ SG, hermitian=True)
        out -= np.einsum("nig,gh,njh->nij", St, inner, St)
    return out


def _seen_modes(B: csc_matrix, gauge: FloatArray) -> NDArray[np.bool_]:
    """(g,) whether ``B`` has curvature along each mode of ``gauge`` (6 n, g): a prior's (the
    drift planes' prior tilts the heights at a cost), against the rounding and the ridge of
    the modes no data see."""
    norms = np.einsum("ig,ig->g", gauge, gauge)
    curvature = np.einsum("ig,ig->g", gauge, np.asarray(B @ gauge))
    top = max(float(B.diagonal().max(initial=0.0)), 1e-300)
    out: NDArray[np.bool_] = curvature > SEEN_MODE * top * np.maximum(norms, 1e-300)
    return out


def _gauge_holds(gauge: FloatArray) -> FloatArray:
    """(6 n,) 1 on the unknowns that, held, fix every mode of ``gauge`` and nothing else: per
    group of modes (the modes that move the same patches), as many unknowns of its first
    patch as it has modes, chosen where the modes move them independently."""
    n = gauge.shape[0] // 6
    moves = gauge.reshape(n, 6, -1)
    support = np.abs(moves).max(axis=1) > 0  # (n, g)
    _, group = np.unique(support.T, axis=0, return_inverse=True)
    holds = np.zeros((n, 6))
    for label in np.unique(group):
        modes = np.flatnonzero(group == label)
        for first in np.flatnonzero(support[:, modes[0]]).tolist():
            block = moves[first][:, modes]
            if np.linalg.matrix_rank(block) == len(modes):
                # the unknowns that best span the modes, by pivoted QR
                _, _, pivots = qr(block.T, pivoting=True, mode="economic")
                holds[first, pivots[: len(modes)]] = 1.0
                break
    out: FloatArray = holds.ravel()
    return out


def _unit_pairs(rows: IntArray, cols: IntArray, n: int) -> IntArray:
    """The distinct pairs (k, 2) of patches, each once, that the triplets' entries join."""
    a, b = np.asarray(rows) // 6, np.asarray(cols) // 6
    key = np.unique(np.minimum(a, b) * n + np.maximum(a, b))
    out: IntArray = np.column_stack([key // n, key % n])
    return out


def translation_sigmas(
    information: tuple[IntArray, IntArray, FloatArray],
    gauge: FloatArray,
    *,
    rms: float,
    z_design: float = 1.0,
    positions: FloatArray | None = None,
    plane_sigma: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Standard deviations of every patch's translation (XY: its larger axis; Z), ``inf`` where
    no data see it: :func:`translation_covariances` times the residual variance ``rms²``.

    Each noise sample enters the information twice (a's points on b's surface and b's points on
    a's), so it counts half; Z variances are further scaled by ``z_design``
    (:func:`merge.core.information.line_design`). ``positions`` (n, 2): where the patches lie,
    for large systems (:func:`translation_covariances`). ``plane_sigma`` (2,): the drift planes'
    prior the refinement solved with (x, y; the unknowns' units,
    :class:`merge.refine.solve.Priors`), added as its steps added it (``rms² / σ²`` per unit
    residual, the data counted twice and the prior per side of them): the uncertainty is then
    that of the posterior the merge found. Without it a large mosaic's Z sigmas were those of
    the data alone, whose patch rows' relative tilts only the scan lines' offsets hold: 2,500
    patches of 64 x 64 px reported 4.5 nm for errors of 0.96 nm (0.18 x), with it 1.2 nm.
    """
    prior = None
    if plane_sigma is not None:
        per_patch = np.zeros((gauge.shape[0] // 6, 6))
        per_patch[:, 4:] = rms**2 / np.asarray(plane_sigma, dtype=np.float64) ** 2
        prior = per_patch.ravel()
    xy_cov, z_var = translation_covariances(*information, gauge, positions=positions, prior=prior)
    rms2 = 2.0 * rms**2
    seen_xy: NDArray[np.bool_] = np.asarray(np.isfinite(xy_cov).all(axis=(1, 2)))
    largest = np.linalg.eigvalsh(np.where(seen_xy[:, None, None], xy_cov, 0.0))[:, 1]
    # a covariance with no positive variance is the rounding of a direction nothing measured
    # (narrow overlaps of a chessboard's faces): not known, rather than NaN
    seen_xy &= largest >= 0
    xy: FloatArray = np.where(seen_xy, np.sqrt(rms2 * np.maximum(largest, 0.0)), np.inf)
    seen_z = np.isfinite(z_var)
    z_var = rms2 * z_design * np.where(seen_z, z_var, 0.0)
    seen_z &= z_var >= 0  # the same for Z
    z: FloatArray = np.where(seen_z, np.sqrt(np.maximum(z_var, 0.0)), np.inf)
    return xy, z


def _diagonal(values: FloatArray) -> csc_matrix:
    idx = np.arange(len(values))
    return coo_matrix((values, (idx, idx)), shape=(len(values), len(values))).tocsc()
