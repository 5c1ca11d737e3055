"""Disk space as a condition of its own: checked before it runs out, recognised when it did.

A full disk shows up in three guises: ``OSError`` with ``ENOSPC`` (or ``EDQUOT``) from a file
write, an h5py error that wraps one, and SQLite's "database or disk is full" through
SQLAlchemy. :func:`is_full` recognises each; :class:`StorageFull` is what the server raises
(HTTP 507), naming the data directory and how much room is needed.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

from sqlalchemy.exc import OperationalError

_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
_FULL_TEXTS = ("database or disk is full", "no space left on device", "disk quota exceeded")


class StorageFull(OSError):
    """The data directory has no room for what must be stored (HTTP 507); says how much."""


def is_full(exc: BaseException) -> bool:
    """Whether ``exc`` (or what caused it) is the disk running out of space."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, StorageFull):
            return True
        if isinstance(current, OSError) and current.errno in _FULL_ERRNOS:
            return True
        text = str(current).lower()
        if isinstance(current, OperationalError | OSError) and any(t in text for t in _FULL_TEXTS):
            return True
        current = current.__cause__ or current.__context__
    return False


def _mb(n: float) -> str:
    return f"{n / 1e6:.0f} MB"


def full_message(
    data_dir: Path, *, need: int = 0, reserve: int = 0, then: str = "resume the run"
) -> str:
    """What an operator reads when the data directory is full: how much is free, how much
    is needed (the next write and the reserve), and what to do."""
    try:
        free = shutil.disk_usage(data_dir).free
    except OSError:
        free = 0
    needed = (
        f"; {_mb(need + reserve)} needed: {_mb(need)} for the next write and a reserve of "
        f"{_mb(reserve)}"
        if need or reserve
        else ""
    )
    return (
        f"the data directory {data_dir} is full ({_mb(free)} free{needed}): free space there, "
        f"then {then}; what is stored is kept"
    )


def check_space(data_dir: Path, *, need: int, reserve: int) -> None:
    """Raise :class:`StorageFull` unless ``need`` bytes fit in ``data_dir`` above ``reserve``."""
    free = shutil.disk_usage(data_dir).free
    if free < need + reserve:
        raise StorageFull(errno.ENOSPC, full_message(data_dir, need=need, reserve=reserve))
