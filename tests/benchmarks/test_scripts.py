"""Every benchmark script answers ``--help`` (argparse %-formats its help texts: a literal
percent sign in one made the variations' script raise instead of printing its usage)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
SCRIPTS = sorted(
    p.name for p in BENCHMARKS.glob("*.py") if "def main(" in p.read_text(encoding="utf-8")
)


def _run(script: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """A benchmark script run with ``args``, its output captured."""
    return subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def test_the_scripts_are_found() -> None:
    assert "merge_variations.py" in SCRIPTS and "merge_scale.py" in SCRIPTS


@pytest.mark.parametrize("script", SCRIPTS)
def test_a_benchmark_prints_its_usage(script: str) -> None:
    done = _run(script, "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage:")


def test_the_bound_names_a_case_it_does_not_know() -> None:
    """``crb.py`` takes the bench's and the grating sweep's cases by name; another is a usage
    error that lists them, before any bound is computed."""
    done = _run("crb.py", "--cases", "paper-r200-p3-s0.6,nope")
    assert done.returncode == 2
    assert "unknown cases nope" in done.stderr
    assert "paper-r200-p3-s0.6" in done.stderr.split("use", 1)[1]


def test_the_scaling_table_writes_json_without_a_400_patch_size(tmp_path: Path) -> None:
    """Without 400 patches to compare with, a size's time ratio is null, not NaN (which no
    strict JSON reader takes); the patches' pixels and scan lines' offsets are as asked."""
    out = tmp_path / "scale.json"
    args = ["--sides", "2", "--pixels", "32", "--line-noise", "0", "--json", str(out)]
    done = _run("merge_scale.py", *args, timeout=300)
    assert done.returncode == 0, done.stderr

    def strict(constant: str) -> None:
        raise ValueError(f"not JSON: {constant}")

    sizes = json.loads(out.read_text(), parse_constant=strict)["sizes"]
    assert [(s["patches"], s["pixels"], s["line_noise_nm"]) for s in sizes] == [(4, 32, 0.0)]
    assert sizes[0]["time_ratio_400"] is None and sizes[0]["patch_ratio_400"] == 0.01
    assert sizes[0]["converged"]


def test_the_scaling_table_prints_the_oracle_beside_the_merge(tmp_path: Path) -> None:
    """``--oracle``: the heights' solve at the true places, scored like the merge."""
    out = tmp_path / "scale.json"
    done = _run("merge_scale.py", "--sides", "2", "--pixels", "32", "--oracle", "--json", str(out))
    assert done.returncode == 0, done.stderr
    assert "oracle: Z" in done.stdout
    size = json.loads(out.read_text())["sizes"][0]
    assert size["oracle_reg_z_nm"] >= 0 and size["oracle_reg_z_rows_nm"] >= 0
    assert 0.5 < size["oracle_map_over_floor"] < 2.0


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--line-noise", "-0.1"], "--line-noise must be >= 0"),
        (["--line-noise", "inf"], "finite"),
        (["--pixels", "4"], "--pixels >= 8"),
        (["--sides", "1"], "sides >= 2"),
    ],
)
def test_the_scaling_table_refuses_sizes_it_cannot_draw(args: list[str], said: str) -> None:
    done = _run("merge_scale.py", *args)
    assert done.returncode == 2
    assert said in done.stderr
