import numpy as np
import pytest
from scipy.sparse import coo_matrix

from backend.synthetic import patch_errors
from merge import run
from merge.report import uncertainty
from merge.report.uncertainty import gauge_modes, tied_groups, translation_covariances
from tests.conftest import Synthetic


def _chain(n: int, link: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triplets of an information matrix: patches in a row, each translation tied to the next
    with weight ``link[i]``; spin and plane of every patch known alone (unit information)."""
    A = np.zeros((6 * n, 6 * n))
    for i, w in enumerate(link):
        for k in range(3):
            a, b = 6 * i + k, 6 * (i + 1) + k
            A[a, a] += w
            A[b, b] += w
            A[a, b] -= w
            A[b, a] -= w
    for c in range(n):
        A[6 * c + 3 : 6 * c + 6, 6 * c + 3 : 6 * c + 6] += np.eye(3)
    rows, cols = np.nonzero(A)
    return rows, cols, A[rows, cols]


@pytest.fixture(params=["dense", "slabs"])
def solver(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Both ways of solving for the covariances (dense LAPACK, diagonal blocks slab by slab)."""
    if request.param == "slabs":
        monkeypatch.setattr(uncertainty, "DENSE_MAX", 0)


@pytest.mark.usefixtures("solver")
def test_a_chain_is_as_uncertain_as_its_weakest_links() -> None:
    n = 5
    link = np.array([4.0, 4.0, 0.01, 4.0])  # one weak link in the middle
    rows, cols, vals = _chain(n, link)
    gauge = np.zeros((6 * n, 3))
    for k in range(3):
        gauge[k::6, k] = 1.0  # common translation only
    xy, z = translation_covariances(rows, cols, vals, gauge)
    laplacian = np.diag(np.r_[link, 0] + np.r_[0, link]) - np.diag(link, 1) - np.diag(link, -1)
    expected = np.diag(np.linalg.pinv(laplacian))
    # the ridge (1e-9 of the largest information) moves them by 1e-6 or so, either way
    np.testing.assert_allclose(xy[:, 0, 0], expected, rtol=3e-6)
    np.testing.assert_allclose(z, expected, rtol=3e-6)
    # each patch is held tightly by a neighbour (own information >= 4: variance <= 0.25 with
    # the others held), yet the halves float against each other (1 / 0.01 = 100 between them,
    # shared 2:3 about the mean): variances of 16 and 36
    assert (xy[:, 0, 0] > 15.0).all()


def test_a_direction_no_data_see_is_infinite() -> None:
    rows, cols, vals = _chain(2, np.array([1.0]))
    keep = ~((rows % 6 == 1) | (cols % 6 == 1))  # nothing about y
    gauge = np.zeros((12, 3))
    for k in range(3):
        gauge[k::6, k] = 1.0
    xy, z = translation_covariances(rows[keep], cols[keep], vals[keep], gauge)
    assert np.isinf(xy[:, 1, 1]).all()
    assert np.isfinite(z).all()


@pytest.mark.usefixtures("solver")
def test_a_patch_no_data_see_leaves_the_others_alone() -> None:
    # the fifth patch is tied to nothing: its translation is unseen, and the gauge (mean motion
    # zero) must not spread its huge variance over the four that are measured
    link = np.array([1.0, 2.0, 1.0, 0.0])
    rows, cols, vals = _chain(5, link)
    gauge = np.zeros((30, 3))
    for k in range(3):
        gauge[k::6, k] = 1.0
    xy, z = translation_covariances(rows, cols, vals, gauge)
    assert np.isinf(np.diag(xy[4])).all() and np.isinf(z[4])
    four = link[:3]
    laplacian = np.diag(np.r_[four, 0] + np.r_[0, four]) - np.diag(four, 1) - np.diag(four, -1)
    np.testing.assert_allclose(xy[:4, 0, 0], np.diag(np.linalg.pinv(laplacian)), rtol=1e-6)


@pytest.mark.usefixtures("solver")
def test_groups_that_overlap_no_other_each_get_their_own_gauge() -> None:
    # a chain of three, a chain of two and a patch that overlaps nothing (no information at
    # all, spin and plane included): each chain is placed as well as if it were alone
    s = np.array([[0, 0, 0], [8, 0, 0], [16, 1, 0], [0, 30, 0], [8, 30, 0], [50, 50, 0]], float)
    radius, weight = np.full(6, 4.0), np.ones(6)
    three, two = _chain(3, np.array([2.0, 0.5])), _chain(2, np.array([1.0]))
    rows = np.concatenate([three[0], two[0] + 18])
    cols = np.concatenate([three[1], two[1] + 18])
    vals = np.concatenate([three[2], two[2]])
    groups = tied_groups(rows, cols, 6)
    assert len(set(groups[:3])) == len(set(groups[3:5])) == 1
    assert len(set(groups)) == 3
    xy, z = translation_covariances(rows, cols, vals, gauge_modes(s, radius, weight, groups))
    for part, idx in ((three, slice(0, 3)), (two, slice(3, 5))):
        alone_xy, alone_z = translation_covariances(
            *part, gauge_modes(s[idx], radius[idx], weight[idx])
        )
        np.testing.assert_allclose(xy[idx], alone_xy, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(z[idx], alone_z, rtol=1e-6, atol=1e-9)
    assert np.isinf(np.diag(xy[5])).all() and np.isinf(z[5])


@pytest.mark.usefixtures("solver")
def test_a_prior_on_the_planes_holds_the_heights_they_tilt() -> None:
    # each patch's height is tied to the next one's through its drift plane (a height
    # difference read at a lever arm): the planes' prior is then what holds the heights, and
    # the covariances are the bordered inverse's with it on the diagonal
    n = 4
    rows, cols, vals = _chain(n, np.array([3.0, 3.0, 3.0]))
    A = coo_matrix((vals, (rows, cols)), shape=(6 * n, 6 * n)).toarray()
    for c in range(n - 1):
        v = np.zeros(6 * n)
        v[6 * c + 2], v[6 * (c + 1) + 2], v[6 * c + 4] = 1.0, -1.0, -1.0
        A += 5.0 * np.outer(v, v)
    gauge = np.zeros((6 * n, 3))
    for k in range(3):
        gauge[k::6, k] = 1.0
    prior = np.zeros((n, 6))
    prior[:, 4:] = 2.0
    at = np.nonzero(A)
    held_xy, held_z = translation_covariances(*at, A[at], gauge, prior=prior.ravel())
    free_xy, free_z = translation_covariances(*at, A[at], gauge)
    K = np.block([[A + np.diag(prior.ravel()), gauge], [gauge.T, np.zeros((3, 3))]])
    expected = np.diag(np.linalg.inv(K))[: 6 * n].reshape(n, 6)
    np.testing.assert_allclose(held_z, expected[:, 2], rtol=1e-5)
    np.testing.assert_allclose(held_xy[:, 0, 0], expected[:, 0], rtol=1e-5)
    # information added: the heights are held better, the places (no plane in them) as before
    assert (held_z < 0.9 * free_z).all()
    np.testing.assert_allclose(held_xy, free_xy, rtol=1e-5)


def _rigid_chain(n: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """An information matrix (6 n, 6 n) of patches in a row 10 apart, each pair's overlap read
    at its midpoint: X, Y against the spin at its lever arm, Z against the plane along x at
    its lever arm, the relative spin and plane along y; every common motion of
    :func:`gauge_modes` costs nothing. And the patches' positions (n, 3)."""
    rng = np.random.default_rng(3)
    s = np.column_stack([10.0 * np.arange(n), np.zeros(n), np.zeros(n)])
    A = np.zeros((6 * n, 6 * n))
    arm = 5.0 / radius  # the midpoint from either centre, in the spin's and plane's units
    # per residual: (unknown, its coefficient in the first patch, in the second)
    residuals = (
        [(0, 1.0, -1.0)],
        [(1, 1.0, -1.0), (3, arm, arm)],
        [(3, 1.0, -1.0)],
        [(2, 1.0, -1.0), (4, arm, arm)],
        [(5, 1.0, -1.0)],
    )
    for c in range(n - 1):
        for terms in residuals:
            v = np.zeros(6 * n)
            for k, first, second in terms:
                v[6 * c + k] += first
                v[6 * (c + 1) + k] += second
            A += rng.uniform(1.0, 5.0) * np.outer(v, v)
    return A, s


@pytest.mark.usefixtures("solver")
def test_a_prior_that_sees_a_common_tilt_leaves_the_gauge_as_the_bordered_inverse_has_it() -> None:
    # the drift planes' prior gives the common tilts of the heights a cost: they are no longer
    # motions no data see, and the slab by slab solution must not move along them freely
    # (400 patches of 256 x 256 px: Z sigmas up to 18 % small that way)
    n, radius = 6, 3.0
    A, s = _rigid_chain(n, radius)
    gauge = gauge_modes(s, np.full(n, radius), np.ones(n))
    assert np.abs(A @ gauge).max() < 1e-12 * np.abs(A).max()
    prior = np.zeros((n, 6))
    prior[:, 4:] = 0.5
    at = np.nonzero(A)
    xy, z = translation_covariances(*at, A[at], gauge, prior=prior.ravel())
    K = np.block([[A + np.diag(prior.ravel()), gauge], [gauge.T, np.zeros((6, 6))]])
    expected = np.diag(np.linalg.inv(K))[: 6 * n].reshape(n, 6)
    np.testing.assert_allclose(z, expected[:, 2], rtol=1e-5)
    np.testing.assert_allclose(xy[:, 1, 1], expected[:, 1], rtol=1e-5)


def test_gauge_modes_are_common_motions() -> None:
    s = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 5.0], [0.0, 10.0, -5.0]])
    G = gauge_modes(s, np.array([2.0, 2.0, 2.0]), np.ones(3))
    assert G.shape == (18, 6)
    np.testing.assert_allclose(np.linalg.norm(G, axis=0), 1.0)
    assert np.linalg.matrix_rank(G) == 6


def test_reported_sigmas_cover_the_errors(small_mosaic: Synthetic) -> None:
    result = run(small_mosaic.patch_set)
    by_id = {p.id: p for p in result.patches}
    synth = small_mosaic.synth
    reports = [by_id[s.id] for s in synth]
    errors = patch_errors(synth, [r.transform for r in reports])
    for e, report in zip(errors, reports, strict=True):
        assert np.hypot(e[0], e[1]) < 4.0 * report.xy_sigma
        assert abs(e[2]) < 4.0 * report.z_sigma
        assert report.xy_sigma < 2e-9 and report.z_sigma < 2e-9


def test_a_covariance_rounded_below_zero_is_unknown(monkeypatch: pytest.MonkeyPatch) -> None:
    # the selected inverse of a direction nothing measured can round to a negative variance
    # (narrow overlaps of a chessboard's faces): its sigma is not known, never NaN
    xy_cov = np.array([np.eye(2), -1e-30 * np.eye(2)])
    z_var = np.array([1.0, -1e-30])
    monkeypatch.setattr(uncertainty, "translation_covariances", lambda *a, **k: (xy_cov, z_var))
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0))
    xy, z = uncertainty.translation_sigmas(empty, np.zeros((12, 0)), rms=1.0)
    assert xy[0] == pytest.approx(np.sqrt(2.0)) and z[0] == pytest.approx(np.sqrt(2.0))
    assert xy[1] == np.inf and z[1] == np.inf
