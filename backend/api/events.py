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
        int, Query(ge=0, le=2**53, description="replay stored events after this id")
    ] = 0,
    follow: Annotated[bool, Query(description="false: send the stored events and end")] = True,
    last_event_id: Annotated[str | None, Header(max_length=20)] = None,
) -> StreamingResponse:
    """Stored events after ``after`` (or ``Last-Event-ID``), then live ones as they happen.
    Each has an ``id``, ``kind`` (run, patch, progress, merge, fault, ...) and JSON data."""
    if last_event_id is not None and last_event_id.strip().isdigit():
        after = min(max(after, int(last_event_id)), 2**53)
    bus = services.events

    async def stream() -> AsyncIterator[str]:
        queue: asyncio.Queue[dict[str, Any] | None] | None = bus.subscribe() if follow else None
        try:
            last = after
            while True:  # stored events first, page by page
                page = await asyncio.to_thread(bus.since, last, run_id=run_id)
                for event in page:
                    last = event["id"]
                    yield _frame(event)
                if len(page) < 1000:
                    break
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
