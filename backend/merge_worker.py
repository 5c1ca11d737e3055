"""The worker process a merge job runs in (:mod:`backend.merge_jobs`) and the live merge's
too (:mod:`backend.live_merge`): the patches as it gets them, its life tied to the server's,
and a worker a killed server left behind reaped at start-up.

A worker merges at a lower priority than the server and the instrument (:data:`WORKER_NICENESS`),
dies with the server (Linux's parent-death signal, :func:`die_with_parent`) and is named in a
pid file meanwhile (:data:`PID_FILE`), so a server that was killed outright, with no time to
stop it, finds and stops it when it starts again (:func:`reap_leftover`).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from multiprocessing.synchronize import Event as MpEvent
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from backend.allocator import share_one_heap, stage_trimmer

if TYPE_CHECKING:
    from merge import Patch

#: Niceness of the worker process: the merge uses every core the server and the instrument
#: leave idle, and yields them whenever those need them.
WORKER_NICENESS = 10


def patch_id(index: int) -> str:
    """The merge's id of a run's patch ``index`` (a merge job's and the live merge's alike)."""
    return f"p{index:03d}"


@dataclass(frozen=True)
class PatchInput:
    """A stored patch as a worker process gets it (picklable, no merge import needed)."""

    id: str
    heights: NDArray[np.float64]
    origin: tuple[float, float]
    pixel_size: tuple[float, float]
    order: int
    row: int
    col: int

    def to_patch(self) -> Patch:
        """The merge's :class:`merge.Patch` (imported here: only workers need it)."""
        from merge import Patch

        return Patch(
            id=self.id,
            heights=self.heights,
            origin=self.origin,
            pixel_size=self.pixel_size,
            order=self.order,
            row=self.row,
            col=self.col,
        )


#: The worker's pid file in the data dir, while a merge runs: start-up reaps what it names.
PID_FILE = "merge-worker.pid"
_PR_SET_PDEATHSIG = 1


def die_with_parent(parent: int) -> None:
    """Ask Linux to kill this process when its parent dies (prctl PR_SET_PDEATHSIG), and
    leave at once if the parent is already gone; elsewhere a no-op."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # no prctl: the pid file still gets it reaped
        return
    if os.getppid() != parent:  # the server died before the request took hold
        os._exit(1)


def reap_leftover(data_dir: Path) -> str | None:
    """Kill a merge worker a previous server left running (named by its pid file, and
    checked to be a Python multiprocessing child); say what was done."""
    pid_file = data_dir / PID_FILE
    try:
        pid = int(pid_file.read_text().strip())
    except (OSError, ValueError):
        return None
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        cmdline = b""
    if not cmdline:
        note = f"the merge worker {pid} of a previous server is gone"
    elif b"multiprocessing" not in cmdline or pid == os.getpid():
        note = f"process {pid} is not a merge worker: left alone"
    else:
        try:
            os.kill(pid, 9)
            note = f"killed merge worker {pid} left running by a previous server"
        except OSError as exc:
            note = f"could not kill merge worker {pid}: {exc}"
    pid_file.unlink(missing_ok=True)
    return note


def merge_child(
    patches: list[PatchInput],
    options: dict[str, Any],
    out: Any,
    cancel: MpEvent,
    parent: int | None = None,
) -> None:
    """Worker process: merge, report progress, send the result (or the error) back; it dies
    with the ``parent`` process (the server) when given."""
    if parent is not None:
        die_with_parent(parent)
    if hasattr(os, "nice"):
        os.nice(WORKER_NICENESS)
    share_one_heap()  # before the merge's threads start
    import merge
    from merge.io.result import result_document

    try:
        patch_set = merge.PatchSet(p.to_patch() for p in patches)
        config = merge.MergeConfig(**options)
        result = merge.run(
            patch_set,
            config,
            progress=lambda it, res: out.put(("progress", it, float(res))),
            cancel=cancel.is_set,
            status=stage_trimmer(
                lambda s: out.put(("status", s.stage, s.detail, s.fraction, s.eta))
            ),
        )
        out.put(("done", result.mosaic.heights, result_document(result, patch_set)))
    except merge.MergeCancelled:
        out.put(("cancelled",))
    except (merge.PatchSetError, ValueError) as exc:
        out.put(("failed", str(exc)))
    except Exception as exc:  # reported to the operator; the server keeps going
        out.put(("failed", f"merge crashed: {type(exc).__name__}: {exc}"))
