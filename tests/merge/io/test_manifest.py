import json
from pathlib import Path

import numpy as np
import pytest

from merge import Patch, PatchSet, PatchSetError, read_patch_set, write_patch_set


def small_set() -> PatchSet:
    rng = np.random.default_rng(0)
    return PatchSet(
        Patch(
            id=f"p{k}",
            heights=rng.normal(size=(4, 5)) * 1e-9,
            origin=(k * 2e-8, 0.0),
            pixel_size=(1e-8, 1e-8),
            order=k,
            row=0,
            col=k,
        )
        for k in range(3)
    )


def test_round_trip(tmp_path: Path) -> None:
    ps = small_set()
    path = write_patch_set(ps, tmp_path)
    back = read_patch_set(path)
    assert back.ids == ps.ids
    for a, b in zip(ps, back, strict=True):
        np.testing.assert_array_equal(a.heights, b.heights)
        assert a.origin == b.origin and a.pixel_size == b.pixel_size
        assert (a.row, a.col, a.order) == (b.row, b.col, b.order)
    assert read_patch_set(tmp_path).ids == ps.ids  # the folder works too


def _edit(tmp_path: Path, change) -> Path:  # type: ignore[no-untyped-def]
    path = write_patch_set(small_set(), tmp_path)
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.update(units="nm"), "units must be 'm'"),
        (lambda d: d.update(format="other/thing@1"), "format"),
        (lambda d: d.update(patches={}), "must be a list"),
        (lambda d: d["patches"][1].pop("origin"), "'p1': missing 'origin'"),
        (lambda d: d["patches"][1].update(file="gone.npy"), "'p1': height file not found"),
        (lambda d: d["patches"][1].update(file="p1.xyz"), "no reader"),
        (lambda d: d["patches"][2].update(id="p0"), "more than once"),
        (
            lambda d: d["patches"][0].update(pixel_size=[0, 1e-8]),
            "'p0': pixel_size must be positive",
        ),
        (lambda d: d["patches"][0].update(order="first"), "'order' must be an integer"),
        (lambda d: d.update(patches=d["patches"][:1]), "at least two"),
    ],
)
def test_manifest_errors_name_the_patch(tmp_path: Path, change, message: str) -> None:  # type: ignore[no-untyped-def]
    path = _edit(tmp_path, change)
    if "xyz" in message or "no reader" in message:
        (tmp_path / "p1.xyz").write_text("x")
    with pytest.raises(PatchSetError, match=message):
        read_patch_set(path)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    path = write_patch_set(small_set(), tmp_path)
    (tmp_path / "p1.npy").write_bytes(b"not numpy at all")
    with pytest.raises(PatchSetError, match="'p1': cannot read"):
        read_patch_set(path)
    np.save(tmp_path / "p1.npy", np.zeros(7))
    with pytest.raises(PatchSetError, match="'p1': heights must be a 2-D"):
        read_patch_set(path)
    path.write_text("{not json")
    with pytest.raises(PatchSetError, match="not valid JSON"):
        read_patch_set(path)
    with pytest.raises(PatchSetError, match="not found"):
        read_patch_set(tmp_path / "missing.json")
