"""A full disk is recognised in each of its guises, and the reserve is checked."""

from __future__ import annotations

import errno
import sqlite3
from pathlib import Path

import pytest
from sqlalchemy.exc import OperationalError

from backend.db.space import StorageFull, check_space, full_message, is_full


def test_every_guise_of_a_full_disk_is_recognised() -> None:
    assert is_full(OSError(errno.ENOSPC, "No space left on device"))
    assert is_full(OSError(errno.EDQUOT, "Disk quota exceeded"))
    full = OperationalError("COMMIT", {}, sqlite3.OperationalError("database or disk is full"))
    assert is_full(full)
    wrapped = RuntimeError("Can't write data")  # h5py wraps the OS error, keeping the cause
    wrapped.__cause__ = OSError(errno.ENOSPC, "no space")
    assert is_full(wrapped)
    assert not is_full(OSError(errno.EACCES, "Permission denied"))
    assert not is_full(ValueError("disk is full of patches"))


def test_the_reserve_is_checked_and_the_message_says_what_to_do(tmp_path: Path) -> None:
    check_space(tmp_path, need=1, reserve=0)
    with pytest.raises(StorageFull) as caught:
        check_space(tmp_path, need=10**6, reserve=10**15)
    assert caught.value.errno == errno.ENOSPC
    assert str(tmp_path) in str(caught.value.strerror) and "reserve" in str(caught.value)
    assert "then merge again" in full_message(tmp_path, then="merge again")
