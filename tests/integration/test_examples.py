"""The scripted-run example works against a real server process."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from backend.server_process import TOKEN, ServerProcess


@pytest.mark.slow
def test_scripted_run_plans_runs_merges_and_downloads(tmp_path: Path) -> None:
    from examples import scripted_run

    server = ServerProcess(tmp_path / "server", MOSAIC_AUTO_MERGE="false").start()
    try:
        code = scripted_run.main(
            ["--url", server.url, "--out", str(tmp_path / "out"), "--token", TOKEN, "--quick"]
        )
    finally:
        server.stop()
    assert code == 0
    heights = np.load(tmp_path / "out" / "mosaic.npy")
    document = json.loads((tmp_path / "out" / "mosaic.json").read_text())
    assert list(heights.shape) == document["shape"] and len(document["patches"]) == 9
