"""Helpers shared by the subcommands: argument parsing of pairs, errors, progress display."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TextIO


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


class ProgressBar:
    """Iteration progress on stderr: a redrawn bar on a terminal, sparse lines otherwise."""

    def __init__(self, total: int, *, stream: TextIO | None = None, label: str = "merge") -> None:
        self.total = max(total, 1)
        self.stream = stream or sys.stderr
        self.label = label
        self.tty = self.stream.isatty()
        self.last = 0.0

    def __call__(self, iteration: int, residual: float) -> None:
        now = time.monotonic()
        if self.tty:
            frac = min(iteration / self.total, 1.0)
            filled = int(30 * frac)
            bar = "#" * filled + "-" * (30 - filled)
            self.stream.write(
                f"\r{self.label} [{bar}] iteration {iteration:4d}"
                f"  residual {residual * 1e9:8.3f} nm"
            )
            self.stream.flush()
        elif now - self.last > 1.0:
            self.stream.write(
                f"{self.label}: iteration {iteration}, residual {residual * 1e9:.3f} nm\n"
            )
            self.last = now

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
