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
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import bmat, coo_matrix, csc_matrix
from scipy.sparse.linalg import splu

from merge.core.overlap import overlap_groups

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Ridge on ``A``, relative to its largest diagonal entry: keeps directions no data see finite.
RIDGE = 1e-9
#: A variance above this fraction of the ridge's own (``1 / ridge``) is a direction no data see.
UNSEEN = 1e-3
#: Information (relative to ``A``'s largest diagonal entry) that holds a translation no data see.
PIN = 1e6
#: Rounds of holding translations no data see.
PASSES = 4
#: Of the variances above the unseen level, those above this fraction of the largest are the
#: unseen translations themselves; the rest are shares the gauge spread from them.
SHARE = 0.25
#: Systems up to this many unknowns are solved dense. The marginal covariances need as many
#: right-hand sides as translations (half the unknowns); LAPACK solves them as one
#: matrix-matrix problem, a sparse LU one column at a time: for 400 patches (2406 unknowns)
#: 0.47 s against 1.40 s. Dense memory and time grow as the square and cube of the size, so
#: larger systems stay sparse (4000 unknowns: a 128 MB matrix).
DENSE_MAX = 4000


def tied_groups(rows: IntArray, cols: IntArray, n: int) -> IntArray:
    """Label (n,) of every patch: which group of patches the information ties together.

    ``rows, cols``: the nonzero entries of the information matrix (6 unknowns per patch).
    Patches that overlap no other (and groups that overlap no other group) have common
    motions of their own that no data see: each group needs a gauge of its own.
    """
    pairs = np.column_stack([np.asarray(rows) // 6, np.asarray(cols) // 6])
    return overlap_groups(np.unique(pairs, axis=0), n)


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
    rows: IntArray, cols: IntArray, vals: FloatArray, gauge: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Marginal covariances of every patch's translation, in units of the residual variance.

    Parameters
    ----------
    rows, cols, vals : arrays
        Triplets of the information matrix ``A`` (6 n x 6 n), duplicates summed.
    gauge : (6 n, g) array
        The common motions (:func:`gauge_modes`), held fixed.

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
    top = max(float(A.diagonal().max(initial=0.0)), 1e-300)
    ridge = RIDGE * top
    unseen = UNSEEN / ridge
    picks = (6 * np.arange(n)[:, None] + np.arange(3)).ravel()
    rhs = np.zeros((size + gauge.shape[1], len(picks)))
    rhs[picks, np.arange(len(picks))] = 1.0
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
        K = bmat(
            [[A + _diagonal(ridge + pin.ravel()), csc_matrix(gauge)], [csc_matrix(gauge.T), None]],
            format="csc",
        )
        X = _solve(K, rhs)[:size]
        block = X[picks].reshape(n, 3, n, 3)[np.arange(n), :, np.arange(n), :]  # (n, 3, 3)
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


def _solve(K: csc_matrix, rhs: FloatArray) -> FloatArray:
    """``K⁻¹ rhs``: dense up to :data:`DENSE_MAX` unknowns, sparse LU beyond."""
    if K.shape[0] <= DENSE_MAX:
        out: FloatArray = np.linalg.solve(K.toarray(), rhs)
        return out
    sparse: FloatArray = splu(K).solve(rhs)
    return sparse


def translation_sigmas(
    information: tuple[IntArray, IntArray, FloatArray],
    gauge: FloatArray,
    *,
    rms: float,
    z_design: float = 1.0,
) -> tuple[FloatArray, FloatArray]:
    """Standard deviations of every patch's translation (XY: its larger axis; Z), ``inf`` where
    no data see it: :func:`translation_covariances` times the residual variance ``rms²``.

    Each noise sample enters the information twice (a's points on b's surface and b's points on
    a's), so it counts half; Z variances are further scaled by ``z_design``
    (:func:`merge.core.information.line_design`).
    """
    xy_cov, z_var = translation_covariances(*information, gauge)
    rms2 = 2.0 * rms**2
    seen_xy: NDArray[np.bool_] = np.asarray(np.isfinite(xy_cov).all(axis=(1, 2)))
    largest = np.linalg.eigvalsh(np.where(seen_xy[:, None, None], xy_cov, 0.0))[:, 1]
    xy: FloatArray = np.where(seen_xy, np.sqrt(rms2 * largest), np.inf)
    seen_z = np.isfinite(z_var)
    z: FloatArray = np.where(
        seen_z, np.sqrt(rms2 * z_design * np.where(seen_z, z_var, 0.0)), np.inf
    )
    return xy, z


def _diagonal(values: FloatArray) -> csc_matrix:
    idx = np.arange(len(values))
    return coo_matrix((values, (idx, idx)), shape=(len(values), len(values))).tocsc()
