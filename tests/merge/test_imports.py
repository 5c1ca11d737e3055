"""What a merging process imports: every CLI merge and merge worker pays for it before it starts
(scipy.stats, for one chi-square quantile, was a third of a second of it)."""

from __future__ import annotations

import subprocess
import sys

#: Packages the merge does not need: heavy to import, or the server's.
NOT_NEEDED = ("scipy.stats", "scipy.optimize", "fastapi", "sqlalchemy", "viser")


def test_the_merge_imports_nothing_it_does_not_need() -> None:
    code = (
        "import sys, merge.pipeline, backend.cli.merge_cmd\n"
        f"print(','.join(m for m in {NOT_NEEDED!r} if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert done.stdout.strip() == ""
