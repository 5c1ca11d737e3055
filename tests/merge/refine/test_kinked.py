"""The cells near a kink: the ringing band's bicubic is the full reconstruction's answer there."""

from __future__ import annotations

import numpy as np

from merge.core.kinks import KINKED, RINGS, subcell_2d
from merge.core.patchset import Patch
from merge.refine import kinked
from merge.refine.bank import SurfaceBank


def test_cells_near_a_kink_are_drawn_as_the_full_reconstruction_draws_them() -> None:
    # a tip-drawn step, its edges 3 degrees off the columns and then off the rows: every look-up
    # in a flagged cell, drawn by its cell's code, against the full sub-cell reconstruction
    yy, xx = np.mgrid[0:40, 0:40].astype(np.float64)
    across = xx * np.cos(np.radians(3.0)) + yy * np.sin(np.radians(3.0))
    rising = 4.0 * np.clip(across - 12.0, 0.0, 7.5)
    patches = [
        Patch("a", rising * 20e-9, (0.0, 0.0), (20e-9, 20e-9)),
        Patch("b", rising.T * 20e-9, (0.0, 0.0), (20e-9, 20e-9)),
    ]
    bank = SurfaceBank(patches, 20e-9, 0.0, 1)
    assert bank.kinks is not None and bank.kinks.cell is not None
    rng = np.random.default_rng(3)
    m = 20000
    dst = rng.integers(0, 2, m)
    u, v = rng.uniform(0, 39, m), rng.uniform(0, 39, m)
    h = np.full(m, np.nan)
    bank.kinks.redraw(bank, dst, u, v, np.ones(m, dtype=bool), h)
    i0, j0 = np.floor(v).astype(np.intp), np.floor(u).astype(np.intp)
    code = bank.kinks.cell[bank.kinks.start[dst] + i0 * 40 + j0]
    assert (code == KINKED).any() and (code == RINGS).any()
    sel = np.flatnonzero(code > 0)
    full, _ = subcell_2d(
        kinked._window(bank, dst[sel], i0[sel], j0[sel]),
        v[sel] - i0[sel],
        u[sel] - j0[sel],
        bank.kinks.threshold[dst[sel]],
    )
    np.testing.assert_allclose(h[sel], full, atol=1e-9)
    assert np.isnan(h[code == 0]).all()  # far from the kinks: the spline's, untouched


def test_a_mosaic_without_kinks_holds_no_codes() -> None:
    rough = np.random.default_rng(4).normal(0.0, 1e-9, (40, 40))
    bank = SurfaceBank([Patch("a", rough, (0.0, 0.0), (20e-9, 20e-9))], 20e-9, 0.0, 1)
    assert bank.kinks is not None and bank.kinks.cell is None
