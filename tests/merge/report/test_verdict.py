"""The merge's verdict line: what it says of the patches whose places are not confirmed."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from merge.report.verdict import verdict


def _result(loose: int, *, n: int = 16, method: str = "default") -> Any:
    patches = [
        SimpleNamespace(
            id=f"p{k:03d}", overlaps=True, correspondences=500, xy_constrained=k >= loose
        )
        for k in range(n)
    ]
    return SimpleNamespace(patches=patches, method=method)


def test_every_place_confirmed_says_every() -> None:
    said = verdict(_result(0))
    assert said.trusted and said.line == (
        "CONFIRMED: every patch's place measured by its overlaps (16 patches)"
    )


def test_a_few_unconfirmed_places_are_named_and_not_called_every_place() -> None:
    said = verdict(_result(1))
    assert said.trusted and said.unconfirmed == ("p000",)
    assert "every" not in said.line
    assert said.line.startswith("CONFIRMED: the places of 15 of 16 patches measured")
    assert "1 not confirmed (p000" in said.line


def test_most_places_unconfirmed_is_not_trusted() -> None:
    said = verdict(_result(9))
    assert not said.trusted and said.line.startswith("NOT TRUSTED: the places of 9 of 16")


def test_a_levelling_method_claims_no_places() -> None:
    said = verdict(_result(16, method="zlevel"))
    assert said.trusted and said.line == "CONFIRMED: Z levelled (16 patches)"
