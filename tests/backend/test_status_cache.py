"""Status documents stay until an event about them, and a render that raced one is dropped."""

from __future__ import annotations

import asyncio

from backend.status_cache import StatusCache


def test_a_run_document_lives_until_an_event_about_that_run() -> None:
    cache = StatusCache()
    body, version = cache.run(1)
    assert body is None
    cache.keep_run(1, version, b"v1")
    assert cache.run(1)[0] == b"v1"
    cache({"run_id": 2, "kind": "progress"})  # another run's news
    assert cache.run(1)[0] == b"v1"
    cache({"run_id": 1, "kind": "progress"})
    assert cache.run(1)[0] is None
    cache.keep_run(1, version, b"stale")  # rendered before that event: not kept
    assert cache.run(1)[0] is None
    _, fresh = cache.run(1)
    cache.keep_run(1, fresh, b"v2")
    cache({"run_id": None, "kind": "recovery"})  # news of no run: every document redone
    assert cache.run(1)[0] is None


def test_clients_missing_at_once_share_one_render() -> None:
    cache = StatusCache()
    calls = []

    def make() -> bytes:
        calls.append(1)
        return b"doc"

    async def many() -> list[bytes]:
        return await asyncio.gather(*(cache.render(("run", 1), make) for _ in range(20)))

    assert asyncio.run(many()) == [b"doc"] * 20
    assert len(calls) == 1
