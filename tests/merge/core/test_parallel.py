"""Sharing blocks among threads."""

from __future__ import annotations

import os
import signal
import threading

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from merge.core import parallel
from merge.core.parallel import WORKERS, each, one_blas_thread


def test_each_item_is_worked_exactly_once() -> None:
    seen: list[int] = []
    each(seen.append, list(range(100)))
    assert sorted(seen) == list(range(100))
    assert WORKERS >= 1


def test_off_the_cores_the_items_are_worked_in_order_on_this_thread(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(parallel, "WORKERS", 2)
    seen: list[tuple[int, int]] = []
    each(lambda i: seen.append((i, threading.get_ident())), list(range(50)), on_cores=False)
    assert seen == [(i, threading.get_ident()) for i in range(50)]


def test_an_error_in_a_block_reaches_the_caller() -> None:
    def work(item: int) -> None:
        if item == 7:
            raise ValueError("block 7")

    with pytest.raises(ValueError, match="block 7"):
        each(work, list(range(10)))


def test_threads_are_kept_between_calls_and_renewed_in_a_forked_child() -> None:
    if WORKERS < 2 or not hasattr(os, "fork"):
        pytest.skip("needs two cores and fork")
    each(lambda _: None, [0, 1])
    before = {t.ident for t in threading.enumerate() if t.name.startswith("merge")}
    each(lambda _: None, [0, 1])
    after = {t.ident for t in threading.enumerate() if t.name.startswith("merge")}
    # the same threads (the pool starts them as work comes, up to WORKERS)
    assert before and before <= after and len(after) <= WORKERS
    pid = os.fork()
    if pid == 0:  # the child: the parent's pool would wait forever on threads it does not have
        signal.alarm(20)  # so a regression fails instead of hanging
        seen: list[int] = []
        each(seen.append, list(range(10)))
        os._exit(0 if sorted(seen) == list(range(10)) else 1)
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def _blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


def test_blas_is_held_to_one_thread_until_the_last_holder_ends() -> None:
    import numpy  # noqa: F401  (its BLAS is loaded)

    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()  # 2 (OpenBLAS takes no more threads than it was built for)
        entered, release = threading.Event(), threading.Event()

        def other_merge() -> None:
            with one_blas_thread():
                entered.set()
                release.wait(10)

        thread = threading.Thread(target=other_merge)
        thread.start()
        assert entered.wait(10)
        assert _blas_threads() == {1}
        with one_blas_thread():
            release.set()
            thread.join(10)
            assert _blas_threads() == {1}  # the other merge ended, this one still runs
        assert _blas_threads() == before


@one_blas_thread()
def _decorated() -> set[int]:
    return _blas_threads()


def test_the_hold_decorates_a_function() -> None:
    assert _decorated() == {1}
