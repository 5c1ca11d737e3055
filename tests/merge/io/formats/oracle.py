"""Gwyddion as the oracle of every reader: its own import, saved as .gwy, read back."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

GWYDDION = shutil.which("gwyddion")
needs_gwyddion = pytest.mark.skipif(GWYDDION is None, reason="gwyddion is not installed")


def gwyddion_convert(src: Path, dst: Path) -> Path:
    """``gwyddion --convert-to-gwy=dst src``: Gwyddion's reading of ``src`` as a .gwy file."""
    subprocess.run(
        [str(GWYDDION), f"--convert-to-gwy={dst}", str(src)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return dst
