"""The SEM-to-stage calibration on the operator's page (a server of its own: the calibration
it makes would place the other page tests' images differently)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from backend.server_process import ServerProcess
from tests.frontend.conftest import _draw_small_roi, _wait
from tests.frontend.test_pages import pytestmark  # noqa: F401  (chromium, slow)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    process = ServerProcess(tmp_path_factory.mktemp("sem-page"), MOSAIC_AUTO_MERGE="false").start()
    yield process
    process.stop()


def test_the_operator_calibrates_and_the_run_says_what_placed_its_roi(
    page: tuple[Any, list[str]], server: ServerProcess
) -> None:
    pg, errors = page
    _wait(pg, "document.querySelector('#sem-calibration').textContent.includes('none')")
    pg.fill("#sem-field", "20")
    pg.click("#sem-calibrate")
    _wait(pg, "document.querySelector('#sem-calibration').textContent.includes('#')")
    said = pg.inner_text("#sem-calibration")
    found = httpx.get(server.url + "/api/sem/calibration").json()
    assert f"#{found['id']}" in said and f"{found['rotation_deg']:.3f}°" in said, said
    pg.click("#sem-acquire")
    pg.wait_for_selector("#sem-canvas[data-sem-id]")
    _draw_small_roi(pg)
    pg.wait_for_selector("#plan-summary[data-count]")
    pg.click("#create-run")
    _wait(pg, "document.querySelector('#run-sem').textContent.includes('calibration #')")
    assert f"calibration #{found['id']}" in pg.inner_text("#run-sem")
    assert errors == [], errors
