"""How much a noisy overlap tells: information with the noise's share taken out.

Pure functions of arrays, shared by the stages. The coarse start weighs a correlation peak by
the texture its overlap shows above the noise (:func:`signal_information`); the refinement's
normal system takes out of every run's information block the part that slopes of the noise
contribute (:func:`noise_share`, :func:`psd_part`) and measures how much one scan line's
residuals move together (:func:`line_design`); the report's uncertainties rest on both.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
#: Float arrays of any width (float32 where the mosaic's memory counts).
Floats = NDArray[np.floating[Any]]


def noise_share(
    w: Floats, arm: FloatArray, starts: IntArray, radius: FloatArray, noise2: FloatArray
) -> FloatArray:
    """Per run, the part of ``Σ w J J'`` (k, 6, 6) that slopes of white noise contribute.

    The destination's slopes enter the Jacobian; their noise (per axis ``noise2`` (k,), the
    variance of a looked-up slope: for bilinear look-ups between independent central
    differences (2/9) σ² / pitch², see :func:`merge.heightfield.slope_noise`) adds, in
    expectation, ``noise2 · Σ w (u0 u0' + u1 u1')`` with ``u0 = (1, 0, 0, -a_y/ρ, 0, 0)`` and
    ``u1 = (0, 1, 0, a_x/ρ, 0, 0)`` (``a`` the lever arm, ``ρ`` (k,) the source's radius).
    Noise is not texture: this share claims precision a flat overlap does not have.
    """
    first = starts[:-1]
    sw = np.add.reduceat(w, first)
    sa = np.add.reduceat(w[:, None] * arm, first, axis=0) / radius[:, None]
    saa = np.add.reduceat(w * np.einsum("ij,ij->i", arm, arm), first) / radius**2
    out = np.zeros((len(first), 6, 6))
    out[:, 0, 0] = out[:, 1, 1] = sw
    out[:, 0, 3] = out[:, 3, 0] = -sa[:, 1]
    out[:, 1, 3] = out[:, 3, 1] = sa[:, 0]
    out[:, 3, 3] = saa
    scaled: FloatArray = out * noise2[:, None, None]
    return scaled


def psd_part(blocks: FloatArray) -> FloatArray:
    """Every symmetric block of ``blocks`` (k, d, d) with its negative eigenvalues set to zero."""
    vals, vecs = np.linalg.eigh(blocks)
    out: FloatArray = np.einsum("kij,kj,klj->kil", vecs, np.clip(vals, 0.0, None), vecs)
    return out


def line_sums(score: FloatArray, groups: IntArray) -> FloatArray:
    """(2,) what :func:`line_design` weighs: the squares of the Z scores ``w r`` (m,) summed by
    scan line of each run (``groups`` (g,) the first row of each, sorted, the first at 0), and
    summed one by one. Sums of blocks of rows add up."""
    if len(score) == 0:
        return np.zeros(2)
    sums = np.add.reduceat(score, groups)
    return np.array([float(sums @ sums), float(score @ score)])


def line_design(sums: FloatArray) -> float:
    """Design effect of the Z scores clustered by scan line within each run, from their
    :func:`line_sums`.

    Per-line offsets (the feedback loop resetting between lines) shift all residuals of one
    source line alike, so they average out far less than white noise: the variance of a Z
    offset is larger than the residuals' count suggests. The ratio of the clustered to the
    independent sum of squared scores measures by how much (1 for white noise).
    """
    clustered, alone = float(sums[0]), float(sums[1])
    return max(clustered / alone, 1.0) if alone > 0 else 1.0


def signal_information(tensor: FloatArray, noise_part: FloatArray | float) -> FloatArray:
    """``tensor - diag(noise_part)``, projected onto the positive semi-definite matrices."""
    noise = np.broadcast_to(np.asarray(noise_part, dtype=np.float64), (len(tensor),))
    out: FloatArray = psd_part((tensor - np.diag(noise))[None])[0]
    return out
