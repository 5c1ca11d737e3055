"""The event stream: every state change, progress report and fault, persisted then published.

Any thread may :meth:`EventBus.emit`; the event is committed to the ``events`` table first
(so a client that reconnects with ``Last-Event-ID`` misses nothing), then handed to every
subscriber's asyncio queue on the server's event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from backend.db.models import Event

log = logging.getLogger("mosaic_afm.events")

#: Events a slow subscriber may fall behind by before it is dropped (it reconnects and replays).
QUEUE_SIZE = 2000


def event_dict(row: Event) -> dict[str, Any]:
    return {
        "id": row.id,
        "time": row.created_at.isoformat(),
        "run_id": row.run_id,
        "kind": row.kind,
        "message": row.message,
        "data": row.data or {},
    }


class EventBus:
    """Persist and publish events."""

    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self._sessions = sessions
        self._lock = threading.Lock()
        self._subscribers: set[asyncio.Queue[dict[str, Any] | None]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._listeners: list[Callable[[dict[str, Any]], None]] = []

    def listen(self, callback: Callable[[dict[str, Any]], None]) -> None:
        """Call ``callback(event)`` on every event, in the emitting thread (keep it quick)."""
        self._listeners.append(callback)

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Publish on ``loop`` (the server's), from whichever thread emits."""
        self._loop = loop

    def emit(
        self, kind: str, message: str, *, run_id: int | None = None, data: dict[str, Any] | None
    ) -> dict[str, Any]:
        """Record an event and publish it; return it as the stream sends it. Where it cannot
        be recorded (a full disk, a damaged database) it is still published, without an id."""
        try:
            with self._sessions() as session:
                row = Event(run_id=run_id, kind=kind, message=message, data=data or {})
                session.add(row)
                session.commit()
                event = event_dict(row)
        except (SQLAlchemyError, OSError):
            log.warning("event %s not recorded: %s", kind, message, exc_info=True)
            return self.publish(kind, message, run_id=run_id, data=data)
        return self._publish(event)

    def publish(
        self, kind: str, message: str, *, run_id: int | None = None, data: dict[str, Any] | None
    ) -> dict[str, Any]:
        """Publish an event that is not recorded (it has no id: a replay will not have it)."""
        event = {
            "id": None,
            "time": datetime.now(UTC).isoformat(),
            "run_id": run_id,
            "kind": kind,
            "message": message,
            "data": data or {},
        }
        return self._publish(event)

    def _publish(self, event: dict[str, Any]) -> dict[str, Any]:
        kind, message = event["kind"], event["message"]
        log.debug("event %s: %s", kind, message)
        for listener in self._listeners:
            try:
                listener(event)
            except Exception:  # a listener's failure is not the emitter's
                log.exception("event listener failed on %s", kind)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with self._lock:
                subscribers = list(self._subscribers)
            for queue in subscribers:
                try:
                    loop.call_soon_threadsafe(self._offer, queue, event)
                except RuntimeError:  # the loop closed meanwhile: nobody is listening
                    break
        return event

    def _offer(self, queue: asyncio.Queue[dict[str, Any] | None], event: dict[str, Any]) -> None:
        if queue.qsize() < QUEUE_SIZE:
            queue.put_nowait(event)
        else:  # the last slot is kept for this: the stream ends, the client replays
            self.unsubscribe(queue)
            queue.put_nowait(None)
            log.warning("an event stream fell %d events behind (not reading): dropped", QUEUE_SIZE)

    def subscribe(self) -> asyncio.Queue[dict[str, Any] | None]:
        queue: asyncio.Queue[dict[str, Any] | None] = asyncio.Queue(maxsize=QUEUE_SIZE + 1)
        with self._lock:
            self._subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[dict[str, Any] | None]) -> None:
        with self._lock:
            self._subscribers.discard(queue)

    def close(self) -> None:
        """End every stream (server shutdown)."""
        with self._lock:
            subscribers = list(self._subscribers)
            self._subscribers.clear()
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        for queue in subscribers:
            with contextlib.suppress(RuntimeError, asyncio.QueueFull):
                loop.call_soon_threadsafe(queue.put_nowait, None)

    def since(
        self, after: int, *, run_id: int | None = None, limit: int = 1000
    ) -> list[dict[str, Any]]:
        """Stored events with id greater than ``after`` (oldest first)."""
        with self._sessions() as session:
            query = select(Event).where(Event.id > after)
            if run_id is not None:
                query = query.where(Event.run_id == run_id)
            rows = session.scalars(query.order_by(Event.id).limit(limit)).all()
            return [event_dict(r) for r in rows]

    def newest(
        self, after: int, *, run_id: int | None = None, limit: int = 1000
    ) -> tuple[list[dict[str, Any]], int]:
        """The newest ``limit`` stored events with id greater than ``after`` (oldest first),
        and how many older ones after ``after`` were left out."""
        with self._sessions() as session:
            query = select(Event).where(Event.id > after)
            if run_id is not None:
                query = query.where(Event.run_id == run_id)
            rows = session.scalars(query.order_by(Event.id.desc()).limit(limit)).all()
            page = [event_dict(r) for r in reversed(rows)]
            if len(rows) < limit:
                return page, 0
            count = select(func.count()).select_from(query.where(Event.id < rows[-1].id).subquery())
            return page, int(session.scalar(count) or 0)

    def latest(self) -> int:
        """The id of the newest stored event, 0 if there is none."""
        with self._sessions() as session:
            newest = session.scalars(select(Event.id).order_by(Event.id.desc()).limit(1)).first()
            return int(newest or 0)
