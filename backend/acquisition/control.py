"""What the API and the acquisition worker say to each other: requests, refusals, and a
failure described for the operator."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from hardware.errors import ProcedureError
from hardware.nanonis.errors import NanonisError
from hardware.smaract_errors import MCSError


class Conflict(RuntimeError):
    """The request cannot be done in the present state (HTTP 409); says why."""


class NotFound(LookupError):
    """No such run (HTTP 404)."""


class Abort(Exception):
    """Raised inside the worker at a checkpoint after an abort request."""


@dataclass
class Control:
    """Requests from the API to the worker of one run."""

    run_id: int
    pause: bool = False
    abort: bool = False
    actor: str = "system"
    reason: str = ""
    shutdown: bool = False  # the server is stopping: the run stays resumable
    #: the worker made the instrument safe and is recording the run's end (its events out)
    concluded: bool = False
    wake: threading.Condition = field(default_factory=threading.Condition)

    def request(self) -> str | None:
        return "abort" if self.abort else "pause" if self.pause else None


def describe(exc: BaseException) -> str:
    """A message an operator understands, for any failure of a step."""
    if isinstance(exc, ProcedureError):
        return str(exc)
    if isinstance(exc, MCSError):
        return f"positioner controller: {exc}"
    if isinstance(exc, NanonisError):
        return f"AFM controller (Nanonis): {exc}"
    if isinstance(exc, OSError):
        return f"instrument link: {exc}"
    return f"unexpected {type(exc).__name__}: {exc} (see the server log)"
