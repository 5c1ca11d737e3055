"""The operator lock: the instrument, and the runs on it, held by one operator at a time.

While it is held, a change to the instrument from anyone else is refused (HTTP 423, the
holder named); its safety actions (abort) are not, and are logged. The holder releases it; an
admin may break it with a reason. It is kept in the database, so a restart keeps it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy.orm import Session, sessionmaker

from backend.db.access_models import LockRecord
from backend.security.authority import Principal

_ROW = 1


@dataclass(frozen=True)
class Holder:
    user_id: int
    name: str
    note: str
    since: datetime

    def says(self) -> str:
        note = f" ({self.note})" if self.note else ""
        return f"{self.name} holds the instrument since {self.since:%Y-%m-%d %H:%M} UTC{note}"


class Locked(Exception):
    """A change refused: someone else holds the lock (HTTP 423)."""

    def __init__(self, holder: Holder, what: str = "the instrument") -> None:
        super().__init__(
            f"{holder.says()}: {what} is theirs until they release the lock "
            "(an admin may break it, DELETE /api/lock with a reason)"
        )
        self.holder = holder


class OperatorLock:
    def __init__(self, sessions: sessionmaker[Session]) -> None:
        self.sessions = sessions
        self._guard = threading.Lock()
        with sessions() as s:
            row = s.get(LockRecord, _ROW)
            self._holder = _holder(row) if row is not None else None

    @property
    def holder(self) -> Holder | None:
        return self._holder

    def other(self, who: Principal) -> Holder | None:
        """The holder, when it is not ``who``."""
        holder = self._holder
        return holder if holder is not None and holder.user_id != who.user_id else None

    def take(self, who: Principal, note: str) -> Holder:
        """Take the lock (or change its note when already held by ``who``)."""
        with self._guard:
            other = self.other(who)
            if other is not None:
                raise Locked(other, "the lock")
            with self.sessions() as s:
                row = s.get(LockRecord, _ROW)
                if row is None:
                    row = LockRecord(id=_ROW, holder_id=who.user_id, holder=who.name, note=note)
                    s.add(row)
                else:
                    row.note = note
                s.commit()
                s.refresh(row)
                self._holder = _holder(row)
            return self._holder

    def release(self, who: Principal, *, force: bool) -> Holder | None:
        """Release the lock (``force``: someone else's); the holder it had, if any."""
        with self._guard:
            holder = self._holder
            if holder is None:
                return None
            if holder.user_id != who.user_id and not force:
                raise Locked(holder, "the lock")
            with self.sessions() as s:
                row = s.get(LockRecord, _ROW)
                if row is not None:
                    s.delete(row)
                    s.commit()
            self._holder = None
            return holder


def _holder(row: LockRecord) -> Holder:
    return Holder(row.holder_id, row.holder, row.note, row.since)
