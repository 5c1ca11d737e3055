"""Asylum .ibw: Igor binary waves (version 5) laid out as Igor's Technical Note 003 gives them,
read by us (through igor2) and by Gwyddion."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from merge.io.formats import FormatError, read_image
from tests.merge.io.formats.oracle import gwyddion_convert, needs_gwyddion

BIN_HEADER, WAVE_HEADER = 64, 320  # bytes, version field included in the first


def write_ibw(
    path: Path,
    layers: np.ndarray,
    labels: list[str],
    *,
    pixel: tuple[float, float],
    first: tuple[float, float],
    note: str = "",
) -> None:
    """A little-endian float32 wave ``data[x, y, layer]`` of ``layers`` (layer, y, x), with the
    layer labels, the x/y scaling and a wave note; the header checksum as Igor writes it."""
    nl, ny, nx = layers.shape
    data = np.transpose(np.asarray(layers, "<f4"), (2, 1, 0)).tobytes(order="F")
    note_bytes = note.encode("latin-1")
    label_bytes = b"".join(s.encode("latin-1").ljust(32, b"\0") for s in ["", *labels])
    wave = bytearray(WAVE_HEADER)
    struct.pack_into("<l", wave, 12, nx * ny * nl)  # npnts
    struct.pack_into("<h", wave, 16, 2)  # type: NT_FP32
    struct.pack_into("<h", wave, 26, 1)  # whVersion
    wave[28:36] = b"scan0001"  # bname
    struct.pack_into("<4l", wave, 68, nx, ny, nl, 0)  # nDim
    struct.pack_into("<4d", wave, 84, pixel[0], pixel[1], 1.0, 1.0)  # sfA
    struct.pack_into("<4d", wave, 116, first[0], first[1], 0.0, 0.0)  # sfB
    wave[148:149] = b"m"  # dataUnits
    wave[152:153] = wave[156:157] = b"m"  # dimUnits of x and y
    head = bytearray(BIN_HEADER)
    struct.pack_into("<h", head, 0, 5)  # version
    struct.pack_into("<l", head, 4, WAVE_HEADER + len(data))  # wfmSize
    struct.pack_into("<l", head, 12, len(note_bytes))  # noteSize
    struct.pack_into("<4l", head, 36, 0, 0, len(label_bytes), 0)  # dimLabelsSize
    head += wave
    total = sum(struct.unpack(f"<{len(head) // 2}h", bytes(head)))
    struct.pack_into("<h", head, 2, (-total + 0x8000) % 0x10000 - 0x8000)  # sums to zero
    path.write_bytes(bytes(head) + data + note_bytes + label_bytes)


def _layers() -> np.ndarray:
    rng = np.random.default_rng(0)
    height = rng.normal(size=(24, 32)) * 1e-9 + np.arange(24)[:, None] * 1e-9  # rises with y
    amplitude = rng.normal(size=(24, 32)) * 1e-10
    phase = rng.normal(size=(24, 32)) * 3.0 + 90.0
    return np.stack([amplitude, height, phase]).astype(np.float32)


LABELS = ["AmplitudeRetrace", "HeightRetrace", "PhaseRetrace"]
NOTE = "ScanSize: 6.4e-08\rXOffset: 1e-07\rYOffset: 2e-07\rScanRate: 1\r"


def test_height_by_default_rows_along_y_wave_scaling(tmp_path: Path) -> None:
    layers = _layers()
    path = tmp_path / "scan0001.ibw"
    write_ibw(path, layers, LABELS, pixel=(2e-9, 3e-9), first=(1e-7, 2e-7), note=NOTE)
    image = read_image(path)
    assert image.channel == "HeightRetrace" and image.channels == tuple(LABELS)
    np.testing.assert_array_equal(image.heights, layers[1].astype(np.float64))
    assert image.pixel_size == (2e-9, 3e-9) and image.offset == (1e-7, 2e-7)
    assert image.unit == "m" and image.metadata["ScanRate"] == "1"
    assert read_image(path, channel="PhaseRetrace").unit == "deg"


@needs_gwyddion
def test_reads_as_gwyddion_reads_it(tmp_path: Path) -> None:
    path = tmp_path / "scan0001.ibw"
    write_ibw(path, _layers(), LABELS, pixel=(2e-9, 3e-9), first=(0.0, 0.0), note=NOTE)
    oracle = gwyddion_convert(path, tmp_path / "oracle.gwy")
    for name in ("HeightRetrace", "AmplitudeRetrace"):
        ours, theirs = read_image(path, channel=name), read_image(oracle, channel=name)
        np.testing.assert_array_equal(ours.heights, theirs.heights)
        assert ours.pixel_size == pytest.approx(theirs.pixel_size, rel=1e-12)


def test_wrong_or_cut_files_are_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "scan.ibw"
    write_ibw(path, _layers(), LABELS, pixel=(2e-9, 3e-9), first=(0.0, 0.0))
    bad = tmp_path / "bad.ibw"
    for content, message in (
        (b"hello", "not an Igor binary wave"),
        (path.read_bytes()[:1000], "truncated or corrupt"),
        (path.read_bytes()[:200], "truncated: the Igor headers"),
    ):
        bad.write_bytes(content)
        with pytest.raises(FormatError, match=message):
            read_image(bad)
    write_ibw(bad, _layers()[:, :1, :], LABELS, pixel=(2e-9, 3e-9), first=(0.0, 0.0))
    with pytest.raises(FormatError, match="holds no image"):
        read_image(bad)
    with pytest.raises(FormatError, match="no channel 'Current'"):
        read_image(path, channel="Current")


def test_import_lays_out_by_wave_offsets_and_merges(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from scipy.ndimage import gaussian_filter

    from backend.cli import main
    from merge import read_result

    rng = np.random.default_rng(1)
    surface = gaussian_filter(rng.normal(size=(40, 70)), 2.0) * 2e-8
    pixel = (1e-8, 1e-8)
    files = []
    for k, col in enumerate((0, 30)):
        part = surface[:, col : col + 40]
        files.append(tmp_path / f"scan{k}.ibw")
        write_ibw(files[-1], part[None], ["HeightRetrace"], pixel=pixel, first=(col * 1e-8, 0.0))
    assert main(["import", *map(str, files), "--out", str(tmp_path / "set")]) == 0
    manifest = tmp_path / "set" / "manifest.json"
    assert main(["merge", str(manifest), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    shifts = [r.t[:2] for r in read_result(tmp_path / "m").transforms.values()]
    assert np.abs(shifts).max() < 1e-9  # the offsets were right: nothing to correct
    capsys.readouterr()
    write_ibw(files[1], surface[None, :, 30:70], ["HeightRetrace"], pixel=pixel, first=(0, 0))
    assert main(["import", *map(str, files), "--out", str(tmp_path / "again")]) == 2
    assert "scan0.ibw, scan1.ibw share one scan offset" in capsys.readouterr().err


def test_a_single_unlabelled_length_wave_is_the_height(tmp_path: Path) -> None:
    layers = _layers()[1:2]
    path = tmp_path / "flattened.ibw"
    write_ibw(path, layers, [], pixel=(2e-9, 2e-9), first=(0.0, 0.0))
    image = read_image(path)
    assert image.channels == ("scan0001 0",) and image.unit == "m"
    np.testing.assert_array_equal(image.heights, layers[0].astype(np.float64))
