"""How a merging process hands freed memory back to the system.

glibc's allocator serves a large block from its heap, not from a mapping of its own, once a
block of that size was freed (the mmap threshold rises with the largest block freed, up to
32 MB), and memory freed inside the heap seldom goes back. A merge allocates and frees arrays
of every size stage after stage, so the process kept the memory of every stage it had passed
(400 patches: 69 bytes per input pixel still held after the coarse start, whose arrays were
all freed, and a peak of 270 against 219 with a fixed threshold). Fixing the threshold at
:data:`MMAP_THRESHOLD` keeps every larger block a mapping of its own, returned when freed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger("mosaic_afm.allocator")

#: Blocks from this many bytes up are mappings of their own (glibc's ``M_MMAP_THRESHOLD``).
MMAP_THRESHOLD = 1 << 20
#: glibc's ``mallopt`` parameter number of the mmap threshold.
M_MMAP_THRESHOLD = -3


def return_large_blocks() -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD` in this process; whether it took
    (False where the C library is not glibc: nothing to do there)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))
    if not done:
        log.warning("the C library refused a fixed mmap threshold: freed memory may be kept")
    return done
