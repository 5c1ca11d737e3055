"""How many cores the merge uses, and a helper that shares independent blocks among them.

numpy and scipy release the GIL inside array operations and FFTs, so threads share the work of
large blocks without copies; every block writes its own output rows, so results never depend on
the order the threads run in. The threads are started once per process and kept: a merge shares
out blocks twice per iteration, and starting fresh threads each time cost more than the small
blocks of a coarse level take.

While a merge runs, BLAS (OpenBLAS, numpy's and scipy's) is held to one thread
(:func:`one_blas_thread`). The merge's products are small (a run's 6 x 6 sums, a slab's blocks):
OpenBLAS shared each among its own threads, which then spun waiting for each other and for the
merge's threads (400 patches of 64 x 64 px on 2 cores: a raw iteration's build 0.72 -> 0.54 s
with the blocks on both cores, and the report's marginal covariances about 0.6 s faster).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TypeVar

from threadpoolctl import OpenBLASController, threadpool_limits

from merge.core.memory import release_freed
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


def each(work: Callable[[T], None], items: Sequence[T], *, on_cores: bool = True) -> None:
    """Call ``work`` on every item, on up to :data:`WORKERS` threads (on this one only, in
    order, unless ``on_cores``); re-raises the first error.

    ``work`` must not call :func:`each` itself (the threads are shared: waiting on them from
    one of them could wait forever).
    """
    if len(items) < 2 or WORKERS < 2 or not on_cores:
        for item in items:
            work(item)
            checkpoint()
        return
    try:
        for _ in _shared_pool().map(work, items):
            checkpoint()  # a cancel stops here; the blocks not begun are dropped
    finally:
        release_freed()  # what the pass's blocks freed stays resident else (merge.core.memory)


_blas_lock = threading.Lock()
_blas_users = 0
_blas_limits: threadpool_limits | None = None


def _take_blas() -> None:
    """Let this thread set OpenBLAS's threads (threadpoolctl lets only the thread that last set
    them do so, and silently ignores the others)."""
    OpenBLASController.clear_controlling_thread(force=True)


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Hold BLAS to one thread within this block (process-wide: BLAS has no per-thread setting).

    Merges running at once in one process, in any of its threads, share the hold: BLAS gets
    its threads back when the last of them ends. Usable as a decorator too.
    """
    global _blas_users, _blas_limits
    with _blas_lock:
        if _blas_users == 0:
            _take_blas()
            _blas_limits = threadpool_limits(limits=1, user_api="blas")
            _take_blas()
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0 and _blas_limits is not None:
                _take_blas()
                _blas_limits.restore_original_limits()
                _take_blas()
                _blas_limits = None
