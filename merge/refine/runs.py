"""The rows of a mosaic's normal system, described run by run and made a block at a time.

A row is one point of a source patch over a destination patch. The points of one source that
may fall on one destination (a directed pair) are those inside the destination's outline, which
on the source's regular point grid is a rectangle: a run is stored as that rectangle, not as its
rows. A mosaic of ten thousand patches has fifty million rows; held as three integers each they
were a sixth of a merge's memory, now a block of runs makes its rows when it is processed
(:meth:`merge.refine.bank.SurfaceBank.rows`) and drops them after.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from merge.core import parallel

IntArray = NDArray[np.intp]

#: Rows per block of the system build (whole runs are kept together), at most; a block holds
#: about 400 bytes a row while it is processed, on each core.
BLOCK_ROWS = 1 << 15
#: Input pixels per row of a block, and the fewest rows of a block: a small mosaic's blocks are
#: smaller, so its working set stays a share of its data (a block on each core: 16 bytes per
#: input pixel). 100 patches of 64 x 64 px: 8,192 rows, the refinement's peak 30 -> 19 MB, 74 ->
#: 47 bytes per input pixel; 400 patches reach the cap. Counted in the patches' pixels, not in
#: the level's rows: the coarse levels, with a quarter of the rows, took four times the blocks.
#: Below 8,192 rows a block's Python-level work outweighs its array work (50 patches of 30 x 60
#: px, one core: a raw step 0.077 s at 4,096 rows, 0.065 at 8,192, 0.063 at 16,384).
PIXELS_PER_BLOCK_ROW, LEAST_BLOCK_ROWS = 50, 8192
#: Rows a block holds before sharing the blocks among the cores pays: a smaller block is many
#: small array operations, between which two threads hand the interpreter to each other. On
#: two cores, a raw step of 50 patches of 30 x 60 px took 0.10-0.11 s on both at 4,096 rows, 0.075
#: s on one; 400 patches of 64 x 64 px at 8,192 rows 0.88-1.03 s on both, 0.80-0.84 on one; 16
#: patches of 200 x 200 px at 12,800 rows 0.083 s on both, 0.11 on one (in blocks twice as
#: large); 400 patches at 16,384 rows 0.67-0.76 s on both, 0.76-0.78 on one.
SHARED_BLOCK_ROWS = 12_000


@dataclass(frozen=True)
class Runs:
    """One run per directed pair: ``src`` and ``dst`` (k,) patches, ``box`` (k, 4) the source's
    point-grid rows ``[i0, i1)`` and columns ``[j0, j1)`` it covers, ``starts`` (k + 1,) the first
    row of every run (rows run line by line, so each line of a run is one group of rows,
    :mod:`merge.refine.lines`). The runs of one source follow each other (a scan line's rows in
    all of them share its offset, and :meth:`blocks` keeps them together)."""

    src: IntArray
    dst: IntArray
    box: IntArray
    starts: IntArray

    @classmethod
    def empty(cls) -> Runs:
        none = np.empty(0, dtype=np.intp)
        return cls(none, none, np.empty((0, 4), dtype=np.intp), np.zeros(1, dtype=np.intp))

    def __len__(self) -> int:
        return len(self.src)

    @property
    def size(self) -> int:
        """Rows in all runs."""
        return int(self.starts[-1])

    def part(self, first: int, last: int) -> Runs:
        """Runs ``[first, last)`` on their own (their rows counted from their first)."""
        return Runs(
            self.src[first:last],
            self.dst[first:last],
            self.box[first:last],
            self.starts[first : last + 1] - self.starts[first],
        )

    def blocks(self, rows: int) -> list[tuple[int, int]]:
        """Ranges ``[first, last)`` of runs holding about ``rows`` rows each: at least one
        source's runs, and never part of one (a block holds every overlap of its sources' scan
        lines, :mod:`merge.refine.lines`)."""
        out = []
        k = len(self)
        # where the source changes: a block ends at one of these
        ends = np.flatnonzero(np.diff(self.src) != 0) + 1
        ends = np.append(ends, k)
        first = 0
        while first < k:
            last = int(np.searchsorted(self.starts, self.starts[first] + rows, side="right")) - 1
            last = max(last, first + 1)
            last = int(ends[np.searchsorted(ends, last)])
            out.append((first, last))
            first = last
        return out

    def groups(self, first: int = 0, last: int | None = None) -> IntArray:
        """First row of every line of runs ``[first, last)``, counted from the first of their
        rows (g,), sorted."""
        last = len(self) if last is None else last
        run, t = self._lines_of(first, last)
        width = self.box[first:last, 3] - self.box[first:last, 2]
        out: IntArray = self.starts[first:last][run] - self.starts[first] + t * width[run]
        return out

    def lines(self, first: int = 0, last: int | None = None) -> IntArray:
        """Which scan line every line of runs ``[first, last)`` is (g,), in the order of
        :meth:`groups`: one number per source patch and point-grid row, the same in every run
        of that source and in every range of runs."""
        last = len(self) if last is None else last
        run, t = self._lines_of(first, last)
        height = int(self.box[:, 1].max()) if len(self) else 0
        out: IntArray = self.src[first:last][run] * height + self.box[first:last, 0][run] + t
        return out

    def _lines_of(self, first: int, last: int) -> tuple[IntArray, IntArray]:
        """Every line of runs ``[first, last)``: its run (counted from ``first``) and its place
        in that run's rectangle (g,) each."""
        lines = self.box[first:last, 1] - self.box[first:last, 0]
        run = np.repeat(np.arange(last - first), lines)
        t = np.arange(int(lines.sum())) - np.repeat(np.cumsum(lines) - lines, lines)
        return run, t


@dataclass(frozen=True)
class RowBlock:
    """The rows of a block of runs: per row (m,) its source and destination patch and its
    point's pixel (``row``, the scan line, and ``col``); ``starts`` (k + 1,) the runs' bounds
    and ``groups`` (g,) the first row of every line of every run, both from the block's first
    row."""

    src: IntArray
    dst: IntArray
    row: IntArray
    col: IntArray
    starts: IntArray
    groups: IntArray

    def __len__(self) -> int:
        return len(self.src)


@dataclass(frozen=True)
class BlockPlan:
    """How the system's rows are built: ``rows`` per block, and whether the blocks are shared
    among the cores (``on_cores``, :func:`merge.core.parallel.each`)."""

    rows: int
    on_cores: bool


def block_plan(pixels: int) -> BlockPlan:
    """The blocks of a mosaic of ``pixels`` input pixels: one of :data:`PIXELS_PER_BLOCK_ROW`
    pixels a row on each core where that holds :data:`SHARED_BLOCK_ROWS` (at most
    :data:`BLOCK_ROWS`); else all on one core, in blocks as large as the cores' would have
    been together (the same working set; :data:`LEAST_BLOCK_ROWS` at least)."""
    per_core = pixels // PIXELS_PER_BLOCK_ROW
    if parallel.WORKERS > 1 and per_core >= SHARED_BLOCK_ROWS:
        return BlockPlan(min(per_core, BLOCK_ROWS), True)
    together = per_core * parallel.WORKERS
    return BlockPlan(int(np.clip(together, LEAST_BLOCK_ROWS, BLOCK_ROWS)), False)
