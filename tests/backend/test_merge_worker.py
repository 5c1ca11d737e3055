"""The merge worker: what runs in the child process a merge job spawns."""

from __future__ import annotations

import queue
import threading
from typing import Any

import pytest

from backend import merge_worker
from backend.merge_worker import WORKER_NICENESS, PatchInput, merge_child
from tests.conftest import Synthetic


def _inputs(mosaic: Synthetic) -> list[PatchInput]:
    return [
        PatchInput(p.id, p.heights, p.origin, p.pixel_size, p.order, p.row, p.col)
        for p in mosaic.patch_set
    ]


def test_the_worker_yields_the_cores_to_the_server_and_sends_the_mosaic(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch
) -> None:
    niced: list[int] = []
    monkeypatch.setattr(merge_worker.os, "nice", lambda inc: niced.append(inc) or inc)
    out: queue.Queue[tuple[Any, ...]] = queue.Queue()
    merge_child(_inputs(small_mosaic), {}, out, threading.Event())  # type: ignore[arg-type]
    messages = list(out.queue)
    assert niced == [WORKER_NICENESS]
    assert {m[0] for m in messages[:-1]} == {"progress", "status"}
    stages = [m[1] for m in messages if m[0] == "status"]
    assert stages[0] == "start" and stages[-1] == "render"
    assert [m[3] for m in messages if m[0] == "status"][-1] == pytest.approx(1.0)
    kind, heights, document = messages[-1]
    assert kind == "done"
    assert heights.ndim == 2 and len(document["patches"]) == len(small_mosaic.patch_set)


def test_a_bad_option_fails_the_job_with_a_message(
    small_mosaic: Synthetic, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(merge_worker.os, "nice", lambda inc: inc)
    out: queue.Queue[tuple[Any, ...]] = queue.Queue()
    merge_child(_inputs(small_mosaic), {"method": "nonsense"}, out, threading.Event())  # type: ignore[arg-type]
    kind, message = out.get_nowait()
    assert kind == "failed" and "nonsense" in message
