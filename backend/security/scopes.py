"""Scopes (what a request may do) and the roles made of them."""

from __future__ import annotations

#: Read everything: runs, patches, merges, SEM images, the instrument, events.
READ = "read"
#: Plan, start, pause, resume, abort and reset runs; re-scan patches; upload patch sets.
RUNS = "runs"
#: Start and cancel merges; register a mosaic on an SEM image.
MERGES = "merges"
#: Acquire, upload and calibrate SEM images.
SEM = "sem"
#: Hold the operator lock; open the 3D viewer's session.
INSTRUMENT = "instrument"
#: Make and revoke one's own API keys, list and end one's own sessions.
KEYS = "keys"
#: The simulator's faults (an admin's test of the instrument's safety).
FAULTS = "faults"
#: Users: add, list, disable.
USERS = "users"
#: Read the audit trail.
AUDIT = "audit"
#: Break another operator's lock (with a reason, logged).
BREAK_LOCK = "lock:break"

ALL = frozenset({READ, RUNS, MERGES, SEM, INSTRUMENT, KEYS, FAULTS, USERS, AUDIT, BREAK_LOCK})

_OBSERVER = frozenset({READ, KEYS})
_OPERATOR = _OBSERVER | {RUNS, MERGES, SEM, INSTRUMENT}

#: The roles: observer (reads), operator (runs the instrument), admin (everything).
ROLES: dict[str, frozenset[str]] = {
    "observer": _OBSERVER,
    "operator": _OPERATOR,
    "admin": ALL,
}


def role_scopes(role: str) -> frozenset[str]:
    """The scopes of ``role``; ValueError for a role that does not exist."""
    try:
        return ROLES[role]
    except KeyError:
        raise ValueError(f"no role {role!r}: one of {', '.join(ROLES)}") from None
