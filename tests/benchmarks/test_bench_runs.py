"""The CLI's wall time and peak memory as the benchmarks measure them: the CLI's own, not the
benchmark process's (Linux starts a forked child's resident high-water mark at its parent's
size, and every grating run of the bench had "peaked" at the bench's 394 MiB)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

# the benchmarks are scripts beside each other, not a package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_runs import run_cli

#: What the caller holds while the CLI runs, MiB: far above what the CLI's help takes.
HELD_MIB = 300


def test_the_peak_is_the_clis_own_not_its_callers() -> None:
    held = np.ones(HELD_MIB * 2**20 // 8)  # written, so resident
    wall, peak, out = run_cli(["--help"])
    assert out.startswith("usage: mosaic-afm")
    assert 0 < peak < HELD_MIB / 2
    assert wall > 0
    assert held[-1] == 1.0


def test_a_failing_cli_raises_with_its_own_message(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="manifest not found") as failed:
        run_cli(["merge", str(tmp_path / "missing.json"), "--out", str(tmp_path / "out")])
    assert str(failed.value).rstrip().endswith(str(tmp_path / "missing.json"))
