"""Handing freed memory back to the system."""

from __future__ import annotations

import subprocess
import sys

import pytest

from merge.core import memory, parallel
from merge.core.memory import release_freed

#: A stage in small: a large array freed (glibc's threshold rises to it), then many medium
#: ones made (from the heap now) and freed behind a small block that holds the heap's top.
STAGE = """
import sys
from pathlib import Path
import numpy as np
from merge.core.memory import release_freed

def rss():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024

big = np.ones(16 << 17)
del big
base = rss()
medium = [np.ones(2 << 17) for _ in range(60)]
pin = np.ones(1000)
del medium
if sys.argv[1] == "trim":
    release_freed()
print(rss() - base)
"""


def _held_after(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", STAGE, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout.strip())


def test_the_memory_a_stage_freed_goes_back_to_the_system() -> None:
    if not release_freed():
        pytest.skip("not glibc: no malloc_trim")
    # 120 MB made and freed: glibc kept a share in its heap (25 MB here); trimmed, none
    assert _held_after("trim") < 4 << 20


def test_a_library_without_trim_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, "_malloc_trim", lambda: None)
    assert release_freed() is False  # nothing to call, nothing raised


def test_each_releases_once_after_a_pass_of_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    if parallel.WORKERS < 2:
        pytest.skip("needs two cores")
    calls: list[int] = []
    monkeypatch.setattr(memory, "_malloc_trim", lambda: lambda: calls.append(0))
    parallel.each(lambda _: None, list(range(50)))
    assert calls == [0]

    def bad(item: int) -> None:
        raise ValueError(f"bad block {item}")

    with pytest.raises(ValueError, match="bad block"):
        parallel.each(bad, [0, 1])
    assert calls == [0, 0]  # after a failed pass too
