"""The 3D viewer's meshes and scene: budgets, precision, one node per patch, merged beside."""

from __future__ import annotations

import numpy as np
import pytest

from backend.server_process import free_port
from backend.viewer import HeightMap, Viewer, decimate, mesh_of


def test_decimation_keeps_the_vertex_budget() -> None:
    heights = np.zeros((2000, 1500))
    out, k = decimate(heights, 1_000_000)
    assert out.size <= 1_000_000 and k == 2
    assert decimate(np.zeros((10, 10)), 1_000_000)[1] == 1


def test_a_large_map_is_shown_as_block_means_not_aliased() -> None:
    # texture at the pixel scale (a period of two pixels): every k-th pixel (k = 3) would show
    # it at full height, aliased to a period of six; the means of blocks of three leave a third
    # of it, each at its block's centre
    jj = np.mgrid[0:3000, 0:2000][1]
    heights = np.where(jj % 2 == 0, 1e-9, -1e-9)
    hmap = HeightMap(heights, (0.0, 0.0), (1e-9, 1e-9))
    verts, _, _, origin = mesh_of(hmap, budget=10**6, zero=0.0)
    assert len(verts) <= 10**6
    assert np.abs(verts[:, 2]).max() == pytest.approx(1e-3 / 3)  # µm
    assert origin == pytest.approx((1e-3, 1e-3))  # half a 3-pixel block, in µm


def test_meshes_are_local_float32_with_vertex_colours_and_skip_nan() -> None:
    xx = np.mgrid[0:20, 0:30][1]
    heights = 1e-6 + 3e-9 * np.sin(xx / 3.0)  # 1 µm up, 3 nm of relief
    heights[5, 5] = np.nan
    far = HeightMap(heights, (5e-3, -4e-3), (10e-9, 10e-9))  # 5 mm from the stage origin
    verts, faces, colours, origin = mesh_of(far, budget=10**6, zero=1e-6)
    assert verts.dtype == np.float32 and origin == (5e3, -4e3)  # µm, kept out of the vertices
    assert np.ptp(verts[:, 2]) * 1e3 == np.float32(np.ptp(verts[:, 2]) * 1e3)  # nm survive
    assert abs(np.ptp(verts[:, 2]) - 6e-3) < 1e-4  # ±3 nm in µm, relative to zero
    assert colours.shape == (600, 3) and colours.dtype == np.uint8
    assert len(faces) == 2 * 19 * 29 - 2 * 4  # the four cells around the NaN are left out


def test_the_scene_holds_one_node_per_patch_and_the_mosaic_beside() -> None:
    viewer = Viewer(port=free_port())
    try:
        hmap = HeightMap(np.zeros((8, 8)), (0.0, 0.0), (0.1e-6, 0.1e-6))
        for i in range(3):
            viewer.show_patch(7, i, hmap, patches=3)
        viewer.show_patch(7, 1, hmap, patches=3)  # a patch shown again replaces its node
        viewer.show_mosaic(2, hmap)
        viewer.show_mosaic(3, hmap)  # a newer merge replaces the older
        names = viewer.node_names()
        assert names["raw"] == [f"/raw/run7/p{i:04d}" for i in range(3)]
        assert names["merged"] == ["/merged/job3"]
        merged = viewer.merged[3]
        assert float(merged.position[0]) > 0.8 + 0.5  # to the right of the raw patches
        viewer.show_patch(8, 0, hmap, patches=1)  # another run clears the raw patches
        assert viewer.node_names()["raw"] == ["/raw/run8/p0000"]
        viewer.exaggeration.value = 40.0
        viewer._restyle()
        assert tuple(viewer.raw[(8, 0)].scale) == (1.0, 1.0, 40.0)
    finally:
        viewer.close()
