"""A merging process hands freed arrays back to the system (``backend.allocator``)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from backend.allocator import return_large_blocks

#: A merge's stages in small: a large array freed, then many medium ones made and freed.
STAGES = """
import sys
from pathlib import Path
import numpy as np
from backend.allocator import return_large_blocks

def rss():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024

if sys.argv[1] == "fixed":
    assert return_large_blocks()
big = np.ones(16 << 17)  # 16 MB: freed, glibc's threshold rises to it
del big
base = rss()
medium = [np.ones(2 << 17) for _ in range(60)]  # 60 x 2 MB
pin = np.ones(1000)  # a small block after them holds the heap's top
del medium
print(rss() - base)
"""


def _held_after(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", STAGES, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout.strip())


def test_freed_arrays_go_back_to_the_system() -> None:
    if not return_large_blocks():
        pytest.skip("not glibc: its allocator's threshold is not ours to fix")
    # 120 MB made and freed: glibc on its own kept 25 MB of them in its heap here; with the
    # threshold fixed, next to nothing is kept
    assert _held_after("fixed") < 4 << 20
