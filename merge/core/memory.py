"""Handing the memory of freed arrays back to the system.

glibc's allocator keeps memory freed inside its heaps for the next allocation, and returns to
the system only the top of a heap past a threshold that rises with the largest array freed.
Within a pass of blocks that is what makes a merge fast (a block's temporaries, a few MB, are
reused without page faults); after it, what the pass freed stays resident while the next pass's
arrays come on top of it. At the peak of a merge of 900 patches of 64 x 64 px, with its threads
on one heap and the heaps trimmed between stages (:mod:`backend.allocator`), the heap still held
27 bytes per input pixel free, of a peak of 58-65. :func:`release_freed` gives such pages back:
:func:`merge.core.parallel.each` calls it when a pass of blocks shared among the cores ends (a
walk over the heaps' free lists, a few milliseconds per merge of 400 patches), not per block; a
small mosaic's passes, on one core, reuse their few megabytes as they are.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable

__all__ = ["c_library", "release_freed"]


@functools.cache
def c_library() -> ctypes.CDLL | None:
    """The process's own C library symbols (opened once, when first needed), or None where
    ctypes cannot open them (Windows)."""
    try:
        return ctypes.CDLL(None)
    except (OSError, TypeError):
        return None


@functools.cache
def _malloc_trim() -> Callable[[], object] | None:
    """glibc's ``malloc_trim(0)``, or None where the C library has none (musl, macOS,
    Windows)."""
    trim = getattr(c_library(), "malloc_trim", None)
    if trim is None:
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return functools.partial(trim, 0)


def release_freed() -> bool:
    """Give the pages of memory this process freed inside its heaps back to the system; whether
    it could (False where the C library cannot)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim()
    return True
