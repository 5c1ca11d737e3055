"""``GET /api/events``: server-sent events of state changes, progress and faults."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query
from fastapi.responses import StreamingResponse

from backend.api.deps import ServicesDep

router = APIRouter(tags=["events"])

#: Seconds between keep-alive comments on a quiet stream.
KEEPALIVE = 15.0
#: Stored events one request replays at most.
REPLAY = 1000


def _frame(event: dict[str, Any]) -> str:
    # an event that could not be recorded has no id: sent without one, it leaves the
    # client's Last-Event-ID where it was
    head = f"id: {event['id']}\n" if event["id"] is not None else ""
    return f"{head}event: {event['kind']}\ndata: {json.dumps(event)}\n\n"


@router.get(
    "/api/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "event stream"}},
)
async def events(
    services: ServicesDep,
    run_id: Annotated[int | None, Query(ge=1, le=2**53, description="only this run")] = None,
    after: Annotated[
        int | None,
        Query(ge=0, le=2**53, description="replay stored events after this id (default: none)"),
    ] = None,
    follow: Annotated[bool, Query(description="false: send stored events and end")] = True,
    last_event_id: Annotated[str | None, Header(max_length=20)] = None,
) -> StreamingResponse:
    """Live events from now on; with ``after`` (or ``Last-Event-ID``) the stored ones after
    that id first, at most :data:`REPLAY` of them (the newest; a comment says how many older
    were left out). ``follow=false`` sends up to :data:`REPLAY` stored events after ``after``
    (default 0) and ends: page through history with the last id sent. Each event has an
    ``id``, ``kind`` (run, patch, progress, merge, fault, ...) and JSON data. A client that
    stops reading is dropped once :data:`~backend.events.QUEUE_SIZE` events wait for it."""
    if last_event_id is not None and last_event_id.strip().isdigit():
        after = min(max(after or 0, int(last_event_id)), 2**53)
    if after is None and not follow:
        after = 0  # history, from the first stored event
    bus = services.events

    def replay(since: int) -> tuple[str, int, int]:
        """Frames of the stored events after ``since`` (off the event loop), the last id
        sent, and how many older ones were left out."""
        if follow:
            page, skipped = bus.newest(since, run_id=run_id, limit=REPLAY)
        else:
            page, skipped = bus.since(since, run_id=run_id, limit=REPLAY), 0
        last = page[-1]["id"] if page else since
        return "".join(_frame(e) for e in page), last, skipped

    async def stream() -> AsyncIterator[str]:
        queue: asyncio.Queue[dict[str, Any] | None] | None = bus.subscribe() if follow else None
        try:
            last = await asyncio.to_thread(bus.latest) if after is None else after
            if after is not None:
                frames, last, skipped = await asyncio.to_thread(replay, after)
                if skipped:
                    yield f": {skipped} older events left out (page them with follow=false)\n\n"
                if frames:
                    yield frames
            if queue is None:
                return
            yield ": live\n\n"
            while True:
                try:
                    item: dict[str, Any] | None = await asyncio.wait_for(queue.get(), KEEPALIVE)
                except TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                if item is None:  # server stopping, or this client fell too far behind
                    return
                if run_id is not None and item["run_id"] != run_id:
                    continue
                if item["id"] is not None:
                    if item["id"] <= last:
                        continue
                    last = item["id"]
                yield _frame(item)
        finally:
            if queue is not None:
                bus.unsubscribe(queue)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-store"}
    )


@router.get("/api/events/latest")
def latest_event(services: ServicesDep) -> dict[str, int]:
    """The id of the newest stored event (0 if none): follow the stream from there."""
    return {"id": services.events.latest()}
