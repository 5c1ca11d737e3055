"""Every route, fed what its OpenAPI schema allows and more, answers 4xx with a detail, never 5xx.

schemathesis generates the requests (with the token, so the bodies get checked too).
The event stream never ends by design and the fault injection is tested on its own.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode

from backend.api.app import create_app
from tests.backend.api.conftest import AUTH, Server, open_server

SKIP = {"/api/events", "/api/instrument/sim/fault"}
#: Operations whose every valid request runs the instrument for seconds (a calibration moves
#: the stage 24 times): fewer valid examples, and time to answer on a busy machine.
SLOW = {"POST /api/sem/calibrate": 3}
OPERATIONS = [
    f"{method.upper()} {path}"
    for path, methods in create_app().openapi()["paths"].items()
    if path not in SKIP
    for method in methods
]


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    yield from open_server(Path(tmp_path_factory.mktemp("fuzz")))


@pytest.fixture(scope="module")
def api_schema(fuzz_server: Server) -> schemathesis.BaseSchema:
    return schemathesis.openapi.from_asgi("/openapi.json", fuzz_server.client.app)


def test_every_route_is_fuzzed() -> None:
    assert len(OPERATIONS) >= 20


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize("label", OPERATIONS)
def test_no_route_answers_a_server_error(
    api_schema: schemathesis.BaseSchema, label: str, mode: GenerationMode
) -> None:
    method, path = label.split(" ", 1)
    operation = api_schema[path][method]

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(
        max_examples=SLOW.get(label, 12) if mode == GenerationMode.POSITIVE else 12,
        deadline=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    def check(case: schemathesis.Case) -> None:
        response = case.call(headers={**AUTH, **(case.headers or {})}, timeout=120)
        assert response.status_code < 500, (label, response.status_code, response.text[:300])
        if response.status_code >= 400:
            assert response.json()["detail"], response.text

    try:
        check()
    except Unsatisfiable:
        assert mode == GenerationMode.NEGATIVE
        pytest.skip(f"{label} has no parameter to get wrong")
