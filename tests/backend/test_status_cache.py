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


def test_an_instrument_status_read_before_a_runs_end_is_not_kept_after_it() -> None:
    """A render begun while the tip was down and finished after the run's last event would
    show "tip engaged" for as long as it was kept: it is dropped, whatever run the event was
    about."""
    cache = StatusCache()
    body, version = cache.instrument()
    assert body is None
    cache({"run_id": 7, "kind": "run"})  # the run ends (its tip retracted) meanwhile
    cache.keep_instrument(version, b'{"safe_state": false}')
    assert cache.instrument()[0] is None
    _, fresh = cache.instrument()
    cache.keep_instrument(fresh, b'{"safe_state": true}')
    assert cache.instrument()[0] == b'{"safe_state": true}'
