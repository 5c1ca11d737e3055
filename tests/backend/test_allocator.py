"""A merging process trims its heaps when a stage ends and keeps its threads on one heap
(``backend.allocator``)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from backend.allocator import stage_trimmer
from merge import Status
from merge.core.memory import release_freed


def test_the_heaps_are_trimmed_when_a_stage_ends(monkeypatch: pytest.MonkeyPatch) -> None:
    trims: list[int] = []
    monkeypatch.setattr("backend.allocator.release_freed", lambda: trims.append(1))
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
    if not release_freed():  # glibc's (the heaps of this process stay as they are)
        pytest.skip("not glibc")
    heaps = {}
    for mode in ("many", "one"):
        done = subprocess.run(
            [sys.executable, "-c", THREADS, mode], capture_output=True, text=True, check=True
        )
        heaps[mode] = sum(line.startswith("Arena ") for line in done.stderr.splitlines())
    # by default the thread took a heap of its own, beside the main one; on one heap, none
    assert heaps == {"many": 2, "one": 1}
