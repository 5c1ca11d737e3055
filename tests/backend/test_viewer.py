"""The 3D viewer's meshes and scene: budgets, precision, one node per patch, merged beside."""

from __future__ import annotations

import time
from collections.abc import Callable

import msgspec
import numpy as np
import pytest
import viser
from viser._messages import GuiUpdateMessage, ViewerCameraMessage
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Origin, Subprotocol

from backend.server_process import free_port
from backend.viewer import HeightMap, Viewer, decimate, mesh_of
from backend.viewer_access import COOKIE, admission, viewer_key


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
        assert viewer.meshes["/merged/job3"].position[0] > 0.8 + 0.5  # right of the raw ones
        viewer.show_patch(8, 0, hmap, patches=1)  # another run clears the raw patches
        assert viewer.node_names()["raw"] == ["/raw/run8/p0000"]
        assert sorted(viewer.meshes) == ["/merged/job3", "/raw/run8/p0000"]
    finally:
        viewer.close()


TOKEN = "viewer-test-token-0123"
API_PORT = 8123


def _browser(port: int, *, origin: str, cookie: str | None) -> ClientConnection:
    """A websocket as the viewer's page opens it (viser's subprotocol)."""
    headers = {"Cookie": f"{COOKIE}={cookie}"} if cookie is not None else {}
    return connect(
        f"ws://127.0.0.1:{port}/",
        origin=Origin(origin),
        additional_headers=headers,
        subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
        open_timeout=10,
    )


def _hello(socket: ClientConnection) -> None:
    """What a browser's viewer sends first (its camera): viser counts it connected then."""
    camera = ViewerCameraMessage(
        (1.0, 0.0, 0.0, 0.0), (0.0, -3.0, 3.0), 1.0, 0.01, 100.0, 480, 640,
        (0.0, 0.0, 0.0), (0.0, 0.0, 1.0),
    )  # fmt: skip
    socket.send(msgspec.msgpack.encode(camera.as_serializable_dict()))


def _closed_with(socket: ClientConnection) -> int | None:
    try:
        while True:
            socket.recv(timeout=10)
    except ConnectionClosed as closed:
        return closed.rcvd.code if closed.rcvd is not None else None


def _wait(until: Callable[[], bool]) -> None:
    deadline = time.monotonic() + 10
    while not until():
        assert time.monotonic() < deadline, "the viewer never got there"
        time.sleep(0.02)


def test_only_this_servers_page_with_the_token_gets_a_view() -> None:
    viewer = Viewer(port=free_port(), admit=admission(token=TOKEN, api_port=API_PORT, origins=[]))
    page = f"http://127.0.0.1:{API_PORT}"
    try:
        for origin, cookie in (
            (page, None),  # no token
            (page, viewer_key("another-token-0123456")),  # a wrong one
            ("http://evil.example", viewer_key(TOKEN)),  # another site's page
            (f"http://127.0.0.1:{API_PORT + 1}", viewer_key(TOKEN)),  # another port's
            (f"http://localhost:{viewer.port}", viewer_key(TOKEN)),  # another host's
        ):
            with _browser(viewer.port, origin=origin, cookie=cookie) as socket:
                assert _closed_with(socket) == 1008, origin
        assert viewer.views == {}
        with _browser(viewer.port, origin=page, cookie=viewer_key(TOKEN)) as socket:
            _hello(socket)
            _wait(lambda: len(viewer.views) == 1)
        own = f"http://127.0.0.1:{viewer.port}"  # the viewer's own page, in the frame
        with _browser(viewer.port, origin=own, cookie=viewer_key(TOKEN)) as socket:
            _hello(socket)
            _wait(lambda: len(viewer.views) == 1)
    finally:
        viewer.close()


def test_each_browser_keeps_its_own_settings_and_values_out_of_range_are_ignored() -> None:
    viewer = Viewer(port=free_port())
    try:
        hmap = HeightMap(np.zeros((8, 8)), (0.0, 0.0), (0.1e-6, 0.1e-6))
        viewer.show_patch(1, 0, hmap, patches=1)
        page = f"http://127.0.0.1:{API_PORT}"
        with (
            _browser(viewer.port, origin=page, cookie=None) as first,
            _browser(viewer.port, origin=page, cookie=None) as second,
        ):
            _hello(first)
            _wait(lambda: len(viewer.views) == 1)
            _hello(second)
            _wait(lambda: len(viewer.views) == 2)
            mine, theirs = (viewer.views[k] for k in sorted(viewer.views))

            def send(value: float) -> None:
                update = GuiUpdateMessage(mine.exaggeration._impl.uuid, {"value": value})
                first.send(msgspec.msgpack.encode(update.as_serializable_dict()))

            for bad in (float("nan"), 1e308, -5.0):
                send(bad)
            send(40.0)
            _wait(lambda: mine.scale == 40.0)
            assert tuple(mine.nodes["/raw/run1/p0000"].scale) == (1.0, 1.0, 40.0)
            assert theirs.scale == 1.0
            assert tuple(theirs.nodes["/raw/run1/p0000"].scale) == (1.0, 1.0, 1.0)
            send(float("inf"))
            time.sleep(0.3)
            assert mine.scale == 40.0  # the last sane value kept
    finally:
        viewer.close()


def test_the_sem_drapes_a_merged_mosaic_for_the_browsers_that_ask_for_it() -> None:
    viewer = Viewer(port=free_port())
    try:
        heights = np.add.outer(np.arange(8.0), np.arange(8.0)) * 1e-9
        hmap = HeightMap(heights, (0.0, 0.0), (0.1e-6, 0.1e-6))
        viewer.show_mosaic(3, hmap)
        viewer.drape(9, hmap, np.ones((8, 8)))  # not the mosaic shown: nothing
        viewer.drape(3, hmap, np.arange(64.0).reshape(8, 8))
        assert viewer.wait_idle()
        assert viewer.node_names()["draped"] == ["/merged/job3-sem"]
        page = f"http://127.0.0.1:{API_PORT}"
        with _browser(viewer.port, origin=page, cookie=None) as socket:
            _hello(socket)
            _wait(lambda: len(viewer.views) == 1)
            view = next(iter(viewer.views.values()))
            _wait(lambda: "/merged/job3-sem" in view.nodes)
            mosaic, drape = view.nodes["/merged/job3"], view.nodes["/merged/job3-sem"]
            assert mosaic.visible and not drape.visible  # heights' colours first
            update = GuiUpdateMessage(view.colour._impl.uuid, {"value": "SEM"})
            socket.send(msgspec.msgpack.encode(update.as_serializable_dict()))
            _wait(lambda: view.tint == "SEM")
            assert drape.visible and not mosaic.visible
        viewer.show_mosaic(4, hmap)  # a new merge takes its drape away
        assert viewer.wait_idle()
        assert viewer.node_names()["draped"] == []
    finally:
        viewer.close()
