import json
import struct
import zlib
from pathlib import Path

import numpy as np

from merge import read_result, run, write_result
from merge.io.png import encode_png, text_mask
from tests.conftest import Synthetic


def test_result_files_follow_the_contract(small_mosaic: Synthetic, tmp_path: Path) -> None:
    result = run(small_mosaic.patch_set)
    write_result(result, tmp_path, patch_set=small_mosaic.patch_set)
    doc = json.loads((tmp_path / "mosaic.json").read_text())
    heights = np.load(tmp_path / "mosaic.npy")
    assert heights.dtype == np.float64 and list(heights.shape) == doc["shape"]
    assert {"origin", "pixel_size", "shape", "patches", "iterations", "converged"} <= doc.keys()
    p0 = doc["patches"][0]
    assert np.array(p0["rotation"]).shape == (3, 3) and len(p0["translation"]) == 3
    assert {"correspondences", "residual_rms", "xy_constrained"} <= p0.keys()
    assert p0["transform"]["model"] == "rigid+zplane"
    back = read_result(tmp_path)
    np.testing.assert_array_equal(back.mosaic.heights, heights)
    # read from the disk as it is used (a read-only view of the mapped file), not copied whole
    assert not back.mosaic.heights.flags.owndata and not back.mosaic.heights.flags.writeable
    tr = back.transforms["p000"]
    np.testing.assert_allclose(tr.slope, result.patches[0].transform.slope)
    png = (tmp_path / "preview.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_png_is_decodable() -> None:
    img = np.zeros((3, 4, 3), dtype=np.uint8)
    img[1, 2] = (10, 20, 30)
    data = encode_png(img)
    width, height = struct.unpack(">II", data[16:24])
    assert (width, height) == (4, 3)
    idat = data[data.index(b"IDAT") + 4 : data.index(b"IEND") - 8]
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(3, 1 + 12)
    assert raw[1, 1 + 6 : 1 + 9].tolist() == [10, 20, 30]
    assert text_mask("1 µm").any()
