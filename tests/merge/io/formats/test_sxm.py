"""Nanonis .sxm: files laid out as the Nanonis manual describes, read by us and by Gwyddion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import FormatError, read_image
from tests.merge.io.formats.oracle import gwyddion_convert, needs_gwyddion


def write_sxm(
    path: Path,
    frames: list[tuple[str, str, np.ndarray, np.ndarray | None]],
    *,
    scan_range: tuple[float, float],
    centre: tuple[float, float],
    up: bool,
) -> None:
    """A minimal .sxm: header blocks, :SCANIT_END:, 0x1A 0x04, big-endian float32 frames
    (each channel forward, then backward when it has one), in stored order."""
    ny, nx = frames[0][2].shape
    info = "\tChannel\tName\tUnit\tDirection\tCalibration\tOffset\n" + "".join(
        f"\t{k}\t{name}\t{unit}\t{'both' if bwd is not None else 'forward'}\t1.0E+0\t0.0E+0\n"
        for k, (name, unit, _, bwd) in enumerate(frames)
    )
    header = (
        ":NANONIS_VERSION:\n2\n:SCANIT_TYPE:\n              FLOAT            MSBFIRST\n"
        f":SCAN_PIXELS:\n       {nx}       {ny}\n"
        f":SCAN_RANGE:\n           {scan_range[0]:.6E}           {scan_range[1]:.6E}\n"
        f":SCAN_OFFSET:\n             {centre[0]:.6E}         {centre[1]:.6E}\n"
        f":SCAN_ANGLE:\n            0.000E+0\n:SCAN_DIR:\n{'up' if up else 'down'}\n"
        f":DATA_INFO:\n{info}\n:SCANIT_END:\n\n\n"
    )
    with path.open("wb") as f:
        f.write(header.encode("latin-1") + b"\x1a\x04")
        for _, _, fwd, bwd in frames:
            f.write(np.asarray(fwd, ">f4").tobytes())
            if bwd is not None:
                f.write(np.asarray(bwd, ">f4").tobytes())


def _frames() -> list[tuple[str, str, np.ndarray, np.ndarray | None]]:
    rng = np.random.default_rng(0)
    z = rng.normal(size=(24, 32)) * 1e-9 + np.arange(24)[:, None] * 3e-10  # rises with the row
    current = rng.normal(size=(24, 32)) * 1e-12
    return [("Z", "m", z, z[:, ::-1]), ("Current", "A", current, None)]


@pytest.mark.parametrize("up", [True, False])
def test_scan_direction_and_backward_lines_are_undone(tmp_path: Path, up: bool) -> None:
    frames = _frames()
    path = tmp_path / "scan.sxm"
    write_sxm(path, frames, scan_range=(64e-9, 48e-9), centre=(1e-7, 2e-7), up=up)
    image = read_image(path)
    stored = frames[0][2].astype(np.float32).astype(np.float64)
    assert image.channel == "Z forward" and image.unit == "m"
    np.testing.assert_array_equal(image.heights, stored if up else stored[::-1])
    backward = read_image(path, channel="Z backward")
    np.testing.assert_array_equal(backward.heights, image.heights)  # same surface
    assert image.pixel_size == pytest.approx((2e-9, 2e-9))
    assert image.offset == pytest.approx((1e-7 - 32e-9 + 1e-9, 2e-7 - 24e-9 + 1e-9))
    assert image.channels == ("Z forward", "Z backward", "Current forward")


@needs_gwyddion
@pytest.mark.parametrize("up", [True, False])
def test_sxm_reads_as_gwyddion_reads_it(tmp_path: Path, up: bool) -> None:
    path = tmp_path / "scan.sxm"
    write_sxm(path, _frames(), scan_range=(64e-9, 48e-9), centre=(1e-7, 2e-7), up=up)
    oracle = gwyddion_convert(path, tmp_path / "oracle.gwy")
    for ours, theirs in (("Z forward", "Z (Forward)"), ("Z backward", "Z (Backward)")):
        a, b = read_image(path, channel=ours), read_image(oracle, channel=theirs)
        np.testing.assert_array_equal(a.heights, b.heights)
        assert a.pixel_size == pytest.approx(b.pixel_size)
        # Gwyddion keeps the Nanonis frame's y (up) as its own y (down the rows): its field's
        # top-left corner is the scan's bottom-left one, a mirror of the scan's place (its
        # picture is the right way up). Ours is the scan's own place: x the same, y mirrored.
        assert a.offset is not None and b.offset is not None
        height = a.heights.shape[0] * a.pixel_size[1]
        assert a.offset[0] == pytest.approx(b.offset[0])
        assert b.offset[1] == pytest.approx(a.pixel_size[1] - height - a.offset[1])


def test_not_an_sxm_or_cut_short(tmp_path: Path) -> None:
    path = tmp_path / "scan.sxm"
    write_sxm(path, _frames(), scan_range=(64e-9, 48e-9), centre=(0, 0), up=True)
    cut = tmp_path / "cut.sxm"
    cut.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(FormatError, match="truncated"):
        read_image(cut, channel="Current forward")
    other = tmp_path / "other.sxm"
    other.write_text("hello")
    with pytest.raises(FormatError, match="not a Nanonis"):
        read_image(other)
    write_sxm(path, _frames()[1:], scan_range=(1e-8, 1e-8), centre=(0, 0), up=True)
    with pytest.raises(FormatError, match="no height channel"):
        read_image(path)
