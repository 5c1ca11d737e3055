"""A merging process hands the memory a finished stage freed back (``backend.allocator``)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from backend.allocator import release_freed_memory, stage_trimmer
from merge import Status

#: A stage in small: a large array freed (glibc's threshold rises to it), then many medium
#: ones made (from the heap now) and freed behind a small block that holds the heap's top.
STAGE = """
import sys
from pathlib import Path
import numpy as np
from backend.allocator import release_freed_memory

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
    release_freed_memory()
print(rss() - base)
"""


def _held_after(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", STAGE, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout.strip())


def test_the_memory_a_stage_freed_goes_back_to_the_system() -> None:
    if not release_freed_memory():
        pytest.skip("not glibc: no malloc_trim")
    # 120 MB made and freed: glibc kept a share in its heap (25 MB here); trimmed, none
    assert _held_after("trim") < 4 << 20


def test_the_heaps_are_trimmed_when_a_stage_ends(monkeypatch: pytest.MonkeyPatch) -> None:
    trims: list[int] = []
    monkeypatch.setattr("backend.allocator.release_freed_memory", lambda: trims.append(1))
    told: list[str] = []
    status = stage_trimmer(lambda s: told.append(s.stage))
    for name in ("start", "start", "refine", "refine", "report", "render"):
        status(Status(name, "", 0.5, 1.0))
    assert len(trims) == 3  # start -> refine -> report -> render
    assert told == ["start", "start", "refine", "refine", "report", "render"]


#: A thread allocates, then glibc's ``malloc_stats`` lists the heaps ("Arena k:") on stderr.
THREADS = """
import ctypes, sys, threading
import numpy as np
from backend.allocator import share_one_heap

if sys.argv[1] == "one":
    share_one_heap()
kept = []
worker = threading.Thread(target=lambda: kept.append(np.ones(1000)))
worker.start()
worker.join()
ctypes.CDLL(None).malloc_stats()
"""


def test_threads_on_one_heap_allocate_from_the_main_one() -> None:
    if not release_freed_memory():  # glibc's (the heaps of this process stay as they are)
        pytest.skip("not glibc")
    heaps = {}
    for mode in ("many", "one"):
        done = subprocess.run(
            [sys.executable, "-c", THREADS, mode], capture_output=True, text=True, check=True
        )
        heaps[mode] = sum(line.startswith("Arena ") for line in done.stderr.splitlines())
    # by default the thread took a heap of its own, beside the main one; on one heap, none
    assert heaps == {"many": 2, "one": 1}
