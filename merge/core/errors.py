"""Exceptions of the merge engine."""

from __future__ import annotations

from collections.abc import Sequence


class PatchSetError(ValueError):
    """A patch set that cannot be merged; the message names the patch and what to fix."""


class MergeCancelled(RuntimeError):
    """The caller asked the merge to stop (``cancel()`` returned true)."""


def listed(names: Sequence[str], most: int = 5) -> str:
    """``names`` for a message: the first ``most`` of them, then how many more."""
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")
