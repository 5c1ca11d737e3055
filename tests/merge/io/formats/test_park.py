"""Park Systems TIFFs written with tifffile as Park lays them out (a preview image, the scan in
private tags), read by us and by Gwyddion."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import FormatError, read_image
from tests.merge.io.formats.oracle import gwyddion_convert, needs_gwyddion

V1, V2 = 0x01000001, 0x01000002


def _text(value: str, chars: int) -> bytes:
    return value.encode("utf-16-le").ljust(2 * chars, b"\0")


def park_header(
    shape: tuple[int, int],
    *,
    size_um: tuple[float, float] = (0.64, 0.48),
    centre_um: tuple[float, float] = (1.5, -2.0),
    gain: float = -2.5,
    scale: float = 1.0,
    offset: float = 0.0,
    unit: str = "um",
    source: str = "Z Height",
    data_type: int | None = None,
    image_type: int = 0,
) -> bytes:
    """The binary header of tag 50435; ``data_type`` given writes the version 2 fields."""
    ny, nx = shape
    fields = [
        struct.pack("<I", image_type), _text(source, 32), _text("NCM", 8), struct.pack("<d", 0),
        struct.pack("<4I", 0, 0, nx, ny), struct.pack("<dId", 0, 0, 0), struct.pack("<3I", 1, 1, 0),
        struct.pack("<4d", *size_um, *centre_um), struct.pack("<2d", 1.0, 0.0), _text("nm", 8),
        struct.pack("<5d", 0, 0, gain, scale, offset), _text(unit, 8),
        struct.pack("<3iI2I", 0, 0, 0, 0, 0, 0),
    ]  # fmt: skip
    if data_type is not None:
        fields += [
            struct.pack("<2d", 1.0, 5.0), _text("High", 8), _text("High", 8), _text("Close", 8),
            struct.pack("<3I", data_type, 0, 0), struct.pack("<2d", 0, 0), _text("AC160TS", 16),
        ]  # fmt: skip
    return b"".join(fields).ljust(580, b"\0")


def write_park(path: Path, data: np.ndarray, header: bytes, version: int) -> None:
    """A Park TIFF: an 8-bit preview as the TIFF image, the scan and header in tags 50432-5."""
    import tifffile

    raw = np.ascontiguousarray(data).tobytes()
    tags = [
        (50432, "I", 1, 0x0E031301, True),
        (50433, "I", 1, version, True),
        (50434, "B", len(raw), raw, True),
        (50435, "B", len(header), header, True),
    ]
    tifffile.imwrite(path, np.zeros((8, 8), np.uint8), extratags=tags, byteorder="<")


def _counts() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.normal(size=(24, 32)) * 300 + np.arange(24)[:, None] * 50  # rises with y


CASES = {  # name: (version, stored dtype, data type of the header)
    "v1 int16": (V1, "<i2", None),
    "v2 int32": (V2, "<i4", 1),
    "v2 float32": (V2, "<f4", 2),
}


@pytest.mark.parametrize("case", CASES)
def test_values_scale_gain_and_layout(tmp_path: Path, case: str) -> None:
    version, dtype, data_type = CASES[case]
    counts = _counts().astype(dtype)
    path = tmp_path / "scan.tiff"
    head = park_header(counts.shape, scale=3.0, offset=7.0, data_type=data_type)
    write_park(path, counts, head, version)
    image = read_image(path)
    # gain * (scale * raw + offset) in µm, the gain negative as it stands
    expected = -2.5 * (3.0 * counts.astype(np.float64) + 7.0) * 1e-6
    np.testing.assert_allclose(image.heights, expected, rtol=1e-12)
    assert image.unit == "m" and image.channel == "Z Height" and image.channels == ("Z Height",)
    assert image.pixel_size == pytest.approx((0.64e-6 / 32, 0.48e-6 / 24))
    dx, dy = image.pixel_size
    assert image.offset == pytest.approx((1.5e-6 - 0.32e-6 + dx / 2, -2e-6 - 0.24e-6 + dy / 2))


@needs_gwyddion
@pytest.mark.parametrize("case", CASES)
def test_reads_as_gwyddion_reads_it(tmp_path: Path, case: str) -> None:
    version, dtype, data_type = CASES[case]
    path = tmp_path / "scan.tiff"
    head = park_header((24, 32), scale=3.0, offset=7.0, data_type=data_type)
    write_park(path, _counts().astype(dtype), head, version)
    ours = read_image(path)
    theirs = read_image(gwyddion_convert(path, tmp_path / "oracle.gwy"))
    np.testing.assert_allclose(ours.heights, theirs.heights, rtol=1e-12, atol=1e-24)
    assert ours.pixel_size == pytest.approx(theirs.pixel_size, rel=1e-12)


def test_foreign_cut_or_unsupported_files_are_clear_errors(tmp_path: Path) -> None:
    counts = _counts().astype("<i2")
    path = tmp_path / "bad.tiff"
    for data, header, version, message in (
        (counts, park_header(counts.shape), 0x01000009, "unsupported Park TIFF version"),
        (counts[:10], park_header(counts.shape), V1, "truncated"),
        (counts, park_header(counts.shape)[:200], V1, "Park header holds 200 bytes"),
        (counts, park_header(counts.shape, image_type=1), V1, "line profile"),
        (counts, park_header(counts.shape, data_type=7), V2, "unknown Park data type"),
        (counts, park_header(counts.shape, source="Amplitude"), V1, "no height channel"),
    ):
        write_park(path, data, header, version)
        with pytest.raises(FormatError, match=message):
            read_image(path)
    write_park(path, counts, park_header(counts.shape, source="Amplitude", unit="V"), V1)
    amplitude = read_image(path, channel="Amplitude")
    assert amplitude.unit == "V"
