"""Helpers shared by the subcommands: argument parsing of pairs, errors, progress display."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from merge import Status


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit code 2."""


def float_pair(text: str) -> tuple[float, float]:
    """``"a,b"`` (or one number for both) as two floats (an argparse type)."""
    parts = [p for p in text.replace(" ", "").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected one or two numbers like 0.5,0.33, got {text!r}"
        ) from None
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2:
        raise argparse.ArgumentTypeError(f"expected one or two numbers like 0.5,0.33, got {text!r}")
    return vals[0], vals[1]


def int_pair(text: str) -> tuple[int, int]:
    """``"nx,ny"`` (or one number for both) as two integers."""
    a, b = float_pair(text)
    if a != int(a) or b != int(b):
        raise argparse.ArgumentTypeError(f"expected whole numbers like 30,60, got {text!r}")
    return int(a), int(b)


def duration(seconds: float) -> str:
    """``"1 h 05 min"``, ``"3 min 20 s"``, ``"12 s"``."""
    s = max(0, round(seconds))
    if s >= 3600:
        return f"{s // 3600} h {s % 3600 // 60:02d} min"
    if s >= 60:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s} s"


class ProgressBar:
    """A merge's progress on stderr: its stage, the share of the whole done, an ETA and the
    last iteration's residual; a redrawn bar on a terminal, a line every few seconds
    otherwise. ``status`` is the merge's ``status`` callback, the bar itself its ``progress``."""

    def __init__(
        self, *, stream: TextIO | None = None, label: str = "merge", every: float = 5.0
    ) -> None:
        self.stream = stream or sys.stderr
        self.label = label
        self.tty = self.stream.isatty()
        self.every = every
        self.last = -float("inf")
        self.stage = ""
        self.residual: float | None = None

    def __call__(self, iteration: int, residual: float) -> None:
        self.residual = residual

    def status(self, s: Status) -> None:
        now = time.monotonic()
        changed = s.stage != self.stage
        self.stage = s.stage
        eta = f", {duration(s.eta)} to go" if s.eta is not None else ""
        res = f", residual {self.residual * 1e9:.3f} nm" if self.residual is not None else ""
        said = f"{s.detail or s.stage}: {100 * s.fraction:3.0f} %{eta}{res}"
        if self.tty:
            filled = int(30 * min(s.fraction, 1.0))
            bar = "#" * filled + "-" * (30 - filled)
            self.stream.write(f"\r{self.label} [{bar}] {said}\x1b[K")
            self.stream.flush()
        elif changed or now - self.last >= self.every:
            self.stream.write(f"{self.label}: {said}\n")
            self.last = now

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
