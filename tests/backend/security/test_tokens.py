from __future__ import annotations

from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from backend.security.throttle import Throttle
from backend.security.tokens import (
    digest,
    key_prefix,
    load_or_create_secret,
    make_access,
    make_key,
    read_access,
)

SECRET = b"s" * 43


def test_an_access_token_reads_back_until_it_expires() -> None:
    token = make_access(SECRET, 7, 1000)
    assert read_access(SECRET, token, 999.0) == (7, 1000)
    assert read_access(SECRET, token, 1000.0) is None
    assert read_access(b"t" * 43, token, 999.0) is None  # another server's secret


@given(st.text(max_size=200))
def test_no_string_but_a_signed_one_reads_as_an_access_token(text: str) -> None:
    assert read_access(SECRET, text, 0.0) is None


def test_a_key_is_found_by_its_prefix_and_stored_as_a_hash() -> None:
    key, prefix, hashed = make_key()
    assert key_prefix(key) == prefix
    assert hashed == digest(key)
    assert prefix in key and hashed not in key
    assert key_prefix("mat.1.2.3") is None


def test_the_secret_file_is_made_once_and_its_owners_only(tmp_path: Path) -> None:
    first = load_or_create_secret(tmp_path)
    assert load_or_create_secret(tmp_path) == first
    assert (tmp_path / "auth_secret").stat().st_mode & 0o077 == 0


def test_the_throttle_doubles_its_pause_and_forgets_a_success() -> None:
    now = [0.0]
    throttle = Throttle(3, first=10.0, clock=lambda: now[0])
    for _ in range(3):
        assert throttle.wait("name:a") == 0
        throttle.failed("name:a")
    assert throttle.wait("name:a") == 10.0
    assert throttle.wait("name:b") == 0
    now[0] = 10.0
    throttle.failed("name:a")
    assert throttle.wait("name:a") == 20.0
    throttle.succeeded("name:a")
    assert throttle.wait("name:a") == 0
