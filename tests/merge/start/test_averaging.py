"""The coarse start's lattice: whole-cell nominal shifts, overlaps, noise and texture."""

from __future__ import annotations

import numpy as np

from merge.core.overlap import overlapping_pairs
from merge.core.patchset import Patch
from merge.start.averaging import averaged_on_lattice
from tests.conftest import Synthetic


def test_neighbours_lie_a_whole_number_of_cells_apart_on_one_lattice(
    small_mosaic: Synthetic,
) -> None:
    patches = small_mosaic.patch_set.patches
    pairs = overlapping_pairs(np.array([p.footprint for p in patches]), margin=0.0)
    cell = 4e-8
    lat = averaged_on_lattice(patches, pairs, cell=cell, max_shift=2e-7)
    for i, (a, b) in enumerate(pairs.tolist()):
        dy, dx = lat.expected(i)
        nominal = np.subtract(patches[a].origin, patches[b].origin) / cell
        assert abs(dx - nominal[0]) <= 1 and abs(dy - nominal[1]) <= 1
    assert (
        lat.nominal_overlap > 0
    ).all()  # 40 % overlaps: every pair that touches overlaps by cells
    assert lat.textured.all() and all(lat.measurable(i) for i in range(len(pairs)))
    assert lat.measurable_pairs().all()
    assert not lat.tilt.any()  # raw scans: no plane to restore


def test_a_patch_of_pure_noise_has_no_texture_to_correlate() -> None:
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:40, 0:40] * 2e-8
    rough = 30e-9 * np.sin(xx / 9e-8) * np.cos(yy / 7e-8)
    patches = [
        Patch("textured", rough + rng.normal(0, 1e-9, rough.shape), (0.0, 0.0), (2e-8, 2e-8)),
        Patch("noise", rng.normal(0, 1e-9, rough.shape), (5e-7, 0.0), (2e-8, 2e-8)),
    ]
    lat = averaged_on_lattice(patches, np.array([[0, 1]]), cell=2e-8, max_shift=2e-7)
    assert lat.textured.tolist() == [True, False]
    assert not lat.measurable(0) and not lat.measurable_pairs().any()
    assert 0.5e-9 < lat.sigma[1] < 2e-9
