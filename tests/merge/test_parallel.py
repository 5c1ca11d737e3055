"""Sharing blocks among threads."""

from __future__ import annotations

import pytest

from merge.parallel import WORKERS, each


def test_each_item_is_worked_exactly_once() -> None:
    seen: list[int] = []
    each(seen.append, list(range(100)))
    assert sorted(seen) == list(range(100))
    assert WORKERS >= 1


def test_an_error_in_a_block_reaches_the_caller() -> None:
    def work(item: int) -> None:
        if item == 7:
            raise ValueError("block 7")

    with pytest.raises(ValueError, match="block 7"):
        each(work, list(range(10)))
