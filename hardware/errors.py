"""Errors of the instrument procedures: what an operator needs to know, typed."""

from __future__ import annotations


class ProcedureError(RuntimeError):
    """A procedure could not complete; the message says what the operator should know."""


class NoSurfaceError(ProcedureError):
    """Landing reached its travel without finding the surface."""


class CrashError(ProcedureError):
    """The tip was driven into the surface (PLL lost in repulsion)."""


class SaturationError(ProcedureError):
    """Z ran out of fine range during a scan: the patch is too tall or tilted."""


class Interrupted(ProcedureError):
    """The caller asked a procedure to stop (an abort); the tip is withdrawn."""


class SafeStateError(ProcedureError):
    """The safe state (loop withdrawn, tip retracted, axes stopped) could not be confirmed."""
