"""How many cores the merge uses, and a helper that shares independent blocks among them.

numpy and scipy release the GIL inside array operations and FFTs, so threads share the work of
large blocks without copies; every block writes its own output rows, so results never depend on
the order the threads run in. The threads are started once per process and kept: a merge shares
out blocks twice per iteration, and starting fresh threads each time cost more than the small
blocks of a coarse level take.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

from merge.core.progress import checkpoint

T = TypeVar("T")


def _cores() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


#: Threads the merge runs at once (the cores this process may use, at most 4).
WORKERS = max(1, min(4, _cores()))


_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _forget_pool() -> None:
    """In a forked child the parent's threads do not exist: start new ones when needed."""
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _shared_pool() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=WORKERS, thread_name_prefix="merge")
        return _pool


def each(work: Callable[[T], None], items: Sequence[T]) -> None:
    """Call ``work`` on every item, on up to :data:`WORKERS` threads; re-raises the first error.

    ``work`` must not call :func:`each` itself (the threads are shared: waiting on them from
    one of them could wait forever).
    """
    if len(items) < 2 or WORKERS < 2:
        for item in items:
            work(item)
            checkpoint()
        return
    for _ in _shared_pool().map(work, items):
        checkpoint()  # a cancel stops here; the blocks not begun are dropped
