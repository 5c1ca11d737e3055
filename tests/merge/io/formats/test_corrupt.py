"""Corrupt files of every format: each read ends in an image or a FormatError, never another
exception (a traceback in the CLI, a 500 from the upload) and never a hang."""

from __future__ import annotations

import random
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import AfmImage, FormatError, read_image
from merge.io.formats.gwy import write_gwy
from tests.merge.io.formats.test_ibw import LABELS, _layers, write_ibw
from tests.merge.io.formats.test_nanoscope import write_nanoscope
from tests.merge.io.formats.test_park import park_header, write_park
from tests.merge.io.formats.test_sxm import _frames, write_sxm

RAW = np.random.default_rng(0).integers(-3000, 3000, (24, 32))
WRITERS: dict[str, Callable[[Path], None]] = {
    "scan.spm": lambda p: write_nanoscope(p, [("Height", RAW, 2, 439.9, "Sens. Zsens", "Trace")]),
    "scan.ibw": lambda p: write_ibw(p, _layers(), LABELS, pixel=(2e-9, 3e-9), first=(0.0, 0.0)),
    "scan.tiff": lambda p: write_park(p, RAW.astype("<i2"), park_header(RAW.shape), 0x01000001),
    "scan.sxm": lambda p: write_sxm(p, _frames(), scan_range=(6e-8, 5e-8), centre=(0, 0), up=True),
    "scan.gwy": lambda p: write_gwy(p, RAW * 1e-12, pixel_size=(1e-8, 1e-8)),
}


def _corruptions(data: bytes, rng: random.Random, count: int) -> list[bytes]:
    out = []
    for k in range(count):
        b = bytearray(data)
        if k % 3 == 0:
            b = b[: rng.randrange(len(b))]  # cut anywhere
        elif k % 3 == 1:
            for _ in range(rng.randint(1, 8)):  # garbage in the headers
                b[rng.randrange(min(len(b), 4000))] = rng.randrange(256)
        else:  # a number of a text header made absurd
            text = bytes(b[:4000]).decode("latin-1")
            spots = [m.span() for m in re.finditer(r"-?\d+", text)]
            if spots:
                lo, hi = rng.choice(spots)
                new = rng.choice(["-1", "0", "999999999", "nan", "1e308"])
                b = bytearray((text[:lo] + new + text[hi:]).encode("latin-1")) + b[4000:]
        out.append(bytes(b))
    return out


@pytest.mark.parametrize("name", WRITERS)
def test_corrupt_files_read_or_fail_clearly(tmp_path: Path, name: str) -> None:
    good = tmp_path / name
    WRITERS[name](good)
    rng = random.Random(name)
    bad = tmp_path / f"bad{good.suffix}"
    for content in _corruptions(good.read_bytes(), rng, 300):
        bad.write_bytes(content)
        outcome: AfmImage | FormatError
        try:
            outcome = read_image(bad)
        except FormatError as exc:
            outcome = exc
        assert isinstance(outcome, AfmImage) or str(bad) in str(outcome)
    assert read_image(good).heights.shape[0] > 1  # a reader is not left broken by bad files
