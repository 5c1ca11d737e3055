"""Bruker NanoScope files laid out as real ones are (header sections, padded header, integer
images), read by us and by Gwyddion."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import FormatError, read_image
from tests.merge.io.formats.oracle import gwyddion_convert, needs_gwyddion

Image = tuple[str, np.ndarray, int, float, str, str]  # name, raw, bytes/pixel, hard V, sens, dir


def write_nanoscope(
    path: Path,
    images: list[Image],
    *,
    scan_size: str = "2 2 ~m",
    offset: tuple[str, str] = ("120 nm", "-80 nm"),
    header_len: int = 8192,
) -> None:
    """A binary NanoScope file: ``\\*File list`` ... ``\\*File list end`` padded to
    ``header_len``, then every image as little-endian integers in stored order. Version 5.12
    files hold 2-byte data, 9.2 files 4-byte data."""
    ny, nx = images[0][1].shape
    version = "0x09200201" if images[0][2] == 4 else "0x05120130"
    lines = [
        "\\*File list",
        f"\\Version: {version}",
        "\\Start context: OL2",
        f"\\Data length: {header_len}",
        "\\*Scanner list",
        "\\Scanner type: Dimension",
        "\\@Sens. Zsens: V 20.00000 nm/V",
        "\\@Sens. Amplitude: V 1.000000 ",
        "\\*Ciao scan list",
        f"\\Scan size: {scan_size.split()[0]} {scan_size.split()[-1]}",
        f"\\X offset: {offset[0]}",
        f"\\Y offset: {offset[1]}",
        f"\\Samps/line: {nx}",
        f"\\Lines: {ny}",
    ]
    position, blobs = header_len, []
    for name, raw, bpp, hard, sens, direction in images:
        lines += [
            "\\*Ciao image list",
            f"\\Data offset: {position}",
            f"\\Data length: {raw.size * bpp}",
            f"\\Bytes/pixel: {bpp}",
            "\\Start context: OL",
            "\\Data type: AFM",
            f"\\Samps/line: {raw.shape[1]}",
            f"\\Number of lines: {raw.shape[0]}",
            "\\Aspect ratio: 1:1",
            f"\\Scan size: {scan_size}",
            f"\\Line direction: {direction}",
            f'\\@2:Image Data: S [{name}] "{name}"',
            f"\\@2:Z scale: V [{sens}] ({hard / 2 ** (8 * bpp):.9f} V/LSB) {hard:.5f} V",
        ]
        blobs.append(raw.astype(f"<i{bpp}").tobytes())
        position += raw.size * bpp
    head = ("\r\n".join([*lines, "\\*File list end"]) + "\r\n").encode("latin-1") + b"\x1a"
    path.write_bytes(head.ljust(header_len, b"\0") + b"".join(blobs))


def _raw(rows: int = 24, cols: int = 32) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(-3000, 3000, (rows, cols)) + np.arange(rows)[:, None] * 500


def test_heights_in_metres_rows_as_stored_offset_at_pixel_centres(tmp_path: Path) -> None:
    raw = _raw()
    path = tmp_path / "scan.spm"
    write_nanoscope(path, [("Height", raw, 2, 439.9, "Sens. Zsens", "Retrace")])
    image = read_image(path)
    # raw / 2^16 * 439.9 V * 20 nm/V
    np.testing.assert_allclose(image.heights, raw / 65536 * 439.9 * 20e-9, rtol=1e-12)
    assert image.unit == "m" and image.channel == "Height"
    assert image.pixel_size == pytest.approx((2e-6 / 32, 2e-6 / 24))
    dx, dy = image.pixel_size
    assert image.offset == pytest.approx((120e-9 - 1e-6 + dx / 2, -80e-9 - 1e-6 + dy / 2))


def test_channels_trace_retrace_and_numbered_suffix(tmp_path: Path) -> None:
    raw = _raw()
    path = tmp_path / "scan.003"  # NanoScope numbers its captures
    write_nanoscope(
        path,
        [
            ("Height", raw, 2, 439.9, "Sens. Zsens", "Trace"),
            ("Height", raw[:, ::-1], 2, 439.9, "Sens. Zsens", "Retrace"),
            ("Amplitude", raw, 2, 0.2, "Sens. Amplitude", "Retrace"),
        ],
    )
    image = read_image(path)
    assert image.channels == ("Height (Trace)", "Height (Retrace)", "Amplitude")
    assert image.channel == "Height (Trace)"
    amplitude = read_image(path, channel="amplitude")
    assert amplitude.unit == "V"
    np.testing.assert_allclose(amplitude.heights, raw / 65536 * 0.2, rtol=1e-12)


@needs_gwyddion
@pytest.mark.parametrize(
    ("bpp", "scan_size", "rows"), [(2, "2 2 ~m", 24), (4, "2 2 ~m", 24), (2, "2 1.5 ~m", 12)]
)
def test_reads_as_gwyddion_reads_it(tmp_path: Path, bpp: int, scan_size: str, rows: int) -> None:
    raw = _raw(rows) * (65536 if bpp == 4 else 1)
    path = tmp_path / "scan.spm"
    height = ("Height", raw, bpp, 439.9, "Sens. Zsens", "Retrace")
    write_nanoscope(path, [height], scan_size=scan_size)
    ours = read_image(path)
    theirs = read_image(gwyddion_convert(path, tmp_path / "oracle.gwy"))
    np.testing.assert_allclose(ours.heights, theirs.heights, rtol=1e-12, atol=0)
    assert ours.pixel_size == pytest.approx(theirs.pixel_size, rel=1e-12)


def test_wrong_cut_or_incomplete_files_are_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "scan.spm"
    write_nanoscope(path, [("Height", _raw(), 2, 439.9, "Sens. Zsens", "Retrace")])
    data = path.read_bytes()
    cases = {
        "not a Bruker": b"hello world",
        "truncated header": data[:500],
        "cut short": data[:-10],
        "ASCII data": b"?" + data[1:],
        "lacks the sensitivity": data.replace(b"\\@Sens. Zsens", b"\\@Sens. Other"),
        "lacks 'data offset'": data.replace(b"\\Data offset", b"\\Data start!"),
    }
    for message, content in cases.items():
        bad = tmp_path / "bad.spm"
        bad.write_bytes(content)
        with pytest.raises(FormatError, match=message):
            read_image(bad)
    with pytest.raises(FormatError, match="no channel 'Phase'"):
        read_image(path, channel="Phase")


def test_numbered_captures_import_and_merge(tmp_path: Path) -> None:
    from scipy.ndimage import gaussian_filter

    from backend.cli import main

    rng = np.random.default_rng(3)
    surface = np.round(gaussian_filter(rng.normal(size=(40, 70)), 2.0) * 20000)
    files = []
    for k, col in enumerate((0, 30)):  # 40 px of 50 nm each: a 2 µm scan, the second 1.5 µm on
        files.append(tmp_path / f"sample.{k:03d}")
        height = ("Height", surface[:, col : col + 40], 2, 439.9, "Sens. Zsens", "Retrace")
        centre = f"{1000 + col * 50} nm"
        write_nanoscope(files[-1], [height], scan_size="2 2 ~m", offset=(centre, "0 nm"))
    assert main(["import", *map(str, files), "--out", str(tmp_path / "set")]) == 0
    manifest = str(tmp_path / "set" / "manifest.json")
    assert main(["merge", manifest, "--out", str(tmp_path / "m"), "--quiet"]) == 0
