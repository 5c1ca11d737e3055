"""Exceptions of the merge engine."""

from __future__ import annotations


class PatchSetError(ValueError):
    """A patch set that cannot be merged; the message names the patch and what to fix."""


class MergeCancelled(RuntimeError):
    """The caller asked the merge to stop (``cancel()`` returned true)."""
