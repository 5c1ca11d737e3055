"""The audit trail: every state change asked for, with who, when, from where, what and how it
ended. Rows are added here and read by ``GET /api/audit``; nothing changes or removes one."""

from __future__ import annotations

import logging
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from backend.db.access_models import AuditRecord

log = logging.getLogger("mosaic_afm.audit")

#: Most rows one read returns.
MOST = 1000


def outcome_of(status: int) -> str:
    """``ok`` for a success; ``refused`` for an identity, scope, lock, throttle or CSRF
    refusal; ``failed`` for any other error."""
    if status < 400:
        return "ok"
    return "refused" if status in (401, 403, 423, 429) else "failed"


def record(
    sessions: sessionmaker[Session],
    *,
    user: str,
    address: str,
    action: str,
    target: str,
    run_id: int | None,
    status: int,
    detail: dict[str, Any],
) -> None:
    """Add a row. Where the database cannot take it (a full disk), the row goes to the
    server's log instead and the answer still leaves: an abort is never held by its record."""
    row = AuditRecord(
        user=user[:64],
        address=address[:64],
        action=action[:64],
        target=target[:300],
        run_id=run_id,
        outcome=outcome_of(status),
        status=status,
        detail=detail,
    )
    try:
        with sessions() as s:
            s.add(row)
            s.commit()
    except (SQLAlchemyError, OSError) as exc:
        log.error(
            "audit row not written (%s): %s %s %s %s %s %s",
            type(exc).__name__,
            row.user,
            row.address,
            row.action,
            row.target,
            status,
            detail,
        )


def read(
    session: Session,
    *,
    user: str | None = None,
    since: datetime | None = None,
    run: int | None = None,
    action: str | None = None,
    limit: int = MOST,
) -> list[AuditRecord]:
    """The newest rows first, filtered by user, time, run and action."""
    query = select(AuditRecord).order_by(AuditRecord.id.desc()).limit(min(limit, MOST))
    if user:
        query = query.where(AuditRecord.user == user)
    if since is not None:
        query = query.where(AuditRecord.at >= since)
    if run is not None:
        query = query.where(AuditRecord.run_id == run)
    if action:
        query = query.where(AuditRecord.action == action)
    return list(session.scalars(query).all())
