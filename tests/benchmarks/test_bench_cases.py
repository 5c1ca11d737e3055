"""How the benchmarks score a merge against its truth (``benchmarks/bench_cases.py``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from merge import PatchTransform, render_mosaic
from tests.conftest import Synthetic

# the benchmarks are scripts beside each other, not a package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_cases import scored_merge


def test_a_merge_is_scored_on_the_patches_its_report_holds(small_mosaic: Synthetic) -> None:
    synth, patches = small_mosaic.synth, small_mosaic.patch_set.patches
    truth = [PatchTransform(s.rotation, s.translation) for s in synth]
    far = list(truth)
    t = np.array(truth[0].t, dtype=float)
    t[0] += 300e-9  # one patch lost, and the report says so
    far[0] = PatchTransform(truth[0].R, t)
    mosaic = render_mosaic(patches, far)
    held = np.ones(len(far), dtype=bool)
    held[0] = False
    surface = small_mosaic.surface
    all_, map_all = scored_merge(synth, far, mosaic, surface)
    among, map_among = scored_merge(synth, far, mosaic, surface, held=held)
    off = np.hypot(*among.patches[:, :2].T)
    # the gauge fitted to the held patches: they are where they belong, the lost one is off
    assert off[1:].max() < 0.5e-9 and off[0] == pytest.approx(300e-9, rel=0.01)
    assert np.hypot(*all_.patches[1:, :2].T).min() > 300e-9 / len(far) / 2
    assert map_among < map_all  # the held part of the map no longer looks tilted
    # every patch held, or none: the gauge of them all
    for every in (np.ones(len(far), dtype=bool), np.zeros(len(far), dtype=bool)):
        same, map_same = scored_merge(synth, far, mosaic, surface, held=every)
        assert same.xy == all_.xy and map_same == map_all
