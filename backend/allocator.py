"""How a merging process hands the memory a finished stage freed back to the system.

glibc's allocator keeps memory freed inside its heaps (every block under its mmap threshold,
which rises with the largest block freed, up to 32 MB) for the next allocation. Within a stage
that is what makes a merge fast: its blocks of rows, a few MB each, are reused without a page
fault. Between stages it is memory held for nothing: 400 patches still held 69 bytes per input
pixel after the coarse start had freed every array it made. A fixed threshold of 1 MB gave
those back (peak 270 -> 219 bytes per pixel) but made every block a fresh mapping: 40 % slower,
the threads queueing on page faults. So the heaps are trimmed (``malloc_trim``) once a stage
ends instead: :func:`stage_trimmer` wraps a merge's ``status`` callback to do it (and the
merge itself trims when a pass of its blocks ends, :mod:`merge.core.memory`).

glibc also gives every thread that allocates a heap of its own (up to eight per core), which
keeps what that thread freed for that thread. The merge's worker threads each make and free a
block's temporaries, so every worker's heap held a block's worth beside the main heap's: on one
heap (:func:`share_one_heap`) what one thread frees the other takes. Patches of 64 x 64 px,
peak bytes per input pixel: 100 patches 64-65 -> 57-58, 400 60-63 -> 55-58, 900 60-63 ->
57-58; the time within 0-4 % (400: 4.9-5.2 s against 4.9-5.1; 900: 11.3-11.6 s against 11.1),
the threads taking one heap's lock a few times per block.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from typing import TYPE_CHECKING

from merge.core.memory import c_library, release_freed

if TYPE_CHECKING:
    from merge import Status


#: ``mallopt``'s parameter for the most heaps (glibc's ``M_ARENA_MAX``).
_M_ARENA_MAX = -8


def share_one_heap() -> bool:
    """Let every thread of this process allocate from one heap (glibc's ``M_ARENA_MAX`` of 1);
    whether it could. Call it before the merge's threads start: a thread that has already
    allocated keeps its heap."""
    mallopt = getattr(c_library(), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_ARENA_MAX, 1))


def stage_trimmer(report: Callable[[Status], None] | None) -> Callable[[Status], None]:
    """A merge ``status`` callback that releases freed memory whenever a stage ends, then
    tells ``report`` (if given)."""
    last = [""]

    def status(s: Status) -> None:
        if s.stage != last[0]:
            if last[0]:
                release_freed()
            last[0] = s.stage
        if report is not None:
            report(s)

    return status
