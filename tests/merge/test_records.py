"""The records the merge's steps hand each other."""

from __future__ import annotations

import pytest

from merge import records


def test_a_stopwatch_sums_the_repeats_of_a_step(monkeypatch: pytest.MonkeyPatch) -> None:
    ticks = iter([1.0, 1.5, 10.0, 10.25, 20.0, 24.0])
    monkeypatch.setattr(records.time, "perf_counter", lambda: next(ticks))
    watch = records.Stopwatch()
    for name in ("solve", "solve", "render"):
        with watch.step(name):
            pass
    assert watch.timings == {"solve": 0.75, "render": 4.0}
