"""How many cores the merge uses, and a helper that shares independent blocks among them.

numpy and scipy release the GIL inside array operations and FFTs, so threads share the work of
large blocks without copies; every block writes its own output rows, so results never depend on
the order the threads run in.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


def _cores() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


#: Threads the merge runs at once (the cores this process may use, at most 4).
WORKERS = max(1, min(4, _cores()))


def each(work: Callable[[T], None], items: Sequence[T]) -> None:
    """Call ``work`` on every item, on up to :data:`WORKERS` threads; re-raises the first error."""
    if len(items) < 2 or WORKERS < 2:
        for item in items:
            work(item)
        return
    with ThreadPoolExecutor(max_workers=WORKERS) as pool:
        list(pool.map(work, items))
