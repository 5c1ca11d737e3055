"""Passwords: local ones hashed with Argon2 (pwdlib), and the host's PAM as a second provider."""

from __future__ import annotations

from pwdlib import PasswordHash
from pwdlib.hashers.argon2 import Argon2Hasher

#: Shortest password a local user may have.
MIN_LENGTH = 8

_HASHER = PasswordHash((Argon2Hasher(),))
#: Checked against when the name is unknown, so a wrong name costs what a wrong password does.
_DECOY = _HASHER.hash("mosaic-afm: no such user")


def hash_password(password: str) -> str:
    """The Argon2 hash of ``password``; ValueError when it is too short to be one."""
    if len(password) < MIN_LENGTH:
        raise ValueError(f"a password needs at least {MIN_LENGTH} characters")
    return _HASHER.hash(password)


def verify_password(password: str, hashed: str | None) -> bool:
    """Whether ``password`` matches ``hashed`` (None: no such user, checked against a decoy
    in the same time, and False)."""
    if hashed is None:
        _HASHER.verify(password, _DECOY)
        return False
    try:
        return _HASHER.verify(password, hashed)
    except Exception:  # a hash pwdlib cannot read: no login, never a crash
        return False
