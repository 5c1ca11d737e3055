"""The 3D viewer: raw patches as they are scanned and merged mosaics, in viser.

Runs in the server process on its own port. Coordinates are micrometres (a local origin per
node, so float32 keeps sub-nm detail); heights are shown with a Z exaggeration the operator
sets (node scale, so no array is sent again). Every node is a mesh with per-vertex colours in
the AFM colour map; a large map is shown as a level of detail (the means of blocks of its
heights) so a scene stays under ~1 M vertices.

Work arrives from the event bus (any thread) and is done on the viewer's own thread, so a
scan or a merge never waits for the browser.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from merge.io.detail import block_means, detail_frame, detail_step
from merge.io.formats.exports import grid_triangles
from merge.io.preview import afm_colors

log = logging.getLogger("mosaic_afm.viewer")

FloatArray = NDArray[np.float64]

#: Vertices allowed for all raw patches of a run together, and for one merged mosaic.
RAW_BUDGET = 1_000_000
MERGED_BUDGET = 1_000_000
UM = 1e6  # scene units per metre
BESIDE_GAP = 1e-6  # between the raw patches and the merged mosaic, metres


@dataclass(frozen=True)
class HeightMap:
    """A height map to show: heights (ny, nx) metres, pixel (i, j) at
    ``origin + (j * dx, i * dy)``."""

    heights: FloatArray
    origin: tuple[float, float]
    pixel_size: tuple[float, float]


def decimate(heights: FloatArray, budget: int) -> tuple[FloatArray, int]:
    """The means of ``k`` x ``k`` blocks (:func:`merge.io.detail.block_means`), ``k`` the least
    that leaves at most ``budget`` points; returns the level of detail and ``k``."""
    k = detail_step(heights.shape, budget)
    if k == 1:
        return np.asarray(heights, dtype=np.float64), 1
    return block_means(heights, k), k


def mesh_of(
    hmap: HeightMap, *, budget: int, zero: float, tint: FloatArray | None = None
) -> tuple[NDArray[np.float32], NDArray[np.uint32], NDArray[np.uint8], tuple[float, float]]:
    """Vertices (µm, local to the map's origin; heights relative to ``zero``), triangles
    over finite cells, vertex colours, and the origin (µm) to place the node at. The colours
    are the heights' in the AFM colour map, or ``tint``'s in grey (an SEM image on the
    heights' grid: the SEM draped over the topography)."""
    heights, k = decimate(hmap.heights, budget)
    ny, nx = heights.shape
    (ox, oy), (px, py) = detail_frame(hmap.origin, hmap.pixel_size, k)
    dx, dy = px * UM, py * UM
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    finite = np.isfinite(heights)
    fill = np.where(finite, heights, np.nanmin(heights) if finite.any() else 0.0)
    verts = np.stack([jj * dx, ii * dy, (fill - zero) * UM], axis=-1).reshape(-1, 3)
    faces = grid_triangles(finite)
    if tint is None:
        lo, hi = np.nanpercentile(heights, [1, 99]) if finite.any() else (0.0, 1.0)
        colours = afm_colors((heights - lo) / max(hi - lo, 1e-12)).reshape(-1, 3)
    else:
        grey, _ = decimate(np.asarray(tint, dtype=np.float64), budget)
        seen = np.isfinite(grey)
        lo, hi = np.nanpercentile(grey, [1, 99]) if seen.any() else (0.0, 1.0)
        level = np.clip(np.nan_to_num((grey - lo) / max(hi - lo, 1e-12)), 0.0, 1.0)
        colours = np.repeat((level * 255 + 0.5).astype(np.uint8)[..., None], 3, axis=-1)
        colours = colours.reshape(-1, 3)
    origin = (ox * UM, oy * UM)
    return verts.astype(np.float32), faces.astype(np.uint32), colours, origin


#: The Z exaggeration a viewer offers, and where it starts.
EXAGGERATION = (1.0, 200.0)
SHOW = ("both", "raw", "merged")
#: What colours a merged mosaic: its heights, or the SEM image it was registered on.
COLOURS = ("height", "SEM")
#: The name of a mosaic's SEM drape: the mosaic's own, with this after it.
DRAPED = "-sem"


@dataclass(frozen=True)
class Shown:
    """One mesh the scene shows, as every browser gets it."""

    mesh: Any  # trimesh.Trimesh
    position: tuple[float, float, float]


class ClientView:
    """What one browser sees: its own nodes of the shared meshes, and its own controls (a
    Z exaggeration, what to show), so that one browser's settings never reach another's."""

    def __init__(self, client: Any, on_reset: Callable[[Any], None]) -> None:
        self.client = client
        self.nodes: dict[str, Any] = {}
        gui = client.gui
        self.exaggeration = gui.add_slider(
            "Z exaggeration", min=EXAGGERATION[0], max=EXAGGERATION[1], step=1.0,
            initial_value=EXAGGERATION[0],
        )  # fmt: skip
        self.show = gui.add_dropdown("Show", SHOW, initial_value=SHOW[0])
        self.colour = gui.add_dropdown("Colour", COLOURS, initial_value=COLOURS[0])
        self.reset = gui.add_button("Reset camera")
        self.scale = EXAGGERATION[0]
        self.mode = SHOW[0]
        self.tint = COLOURS[0]
        self.exaggeration.on_update(self._on_update)
        self.show.on_update(self._on_update)
        self.colour.on_update(self._on_update)
        self.reset.on_click(lambda _: on_reset(client))

    async def _on_update(self, _event: Any) -> None:
        # A coroutine runs on viser's event loop, between one message and the next: the value
        # read is the one this message set. A plain callback runs in a thread pool, where a
        # rejected value's put-back can land after, and undo, a sane one sent just behind it.
        self._changed()

    def _changed(self) -> None:
        """Take the controls' values where they are sane; put back the last sane ones
        where they are not (a NaN or 1e308 sent by hand)."""
        value, mode = self.exaggeration.value, self.show.value
        lo, hi = EXAGGERATION
        if isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi:
            self.scale = float(value)
        else:
            log.warning("viewer: a client sent Z exaggeration %r: ignored", value)
            self.exaggeration.value = self.scale
        if mode in SHOW:
            self.mode = str(mode)
        else:
            self.show.value = self.mode
        if self.colour.value in COLOURS:
            self.tint = str(self.colour.value)
        else:
            self.colour.value = self.tint
        for node in self.nodes.values():
            self.style(node)

    def style(self, node: Any) -> None:
        name = node.name
        merged = name.startswith("/merged/")
        shown = self.mode == "both" or self.mode == ("merged" if merged else "raw")
        if name.endswith(DRAPED):  # the SEM over a mosaic: in its place, when asked for
            shown = shown and self.tint == "SEM"
        elif merged and name + DRAPED in self.nodes:
            shown = shown and self.tint != "SEM"
        node.visible = shown
        node.scale = (1.0, 1.0, self.scale)

    def put(self, name: str, shown: Shown) -> None:
        node = self.client.scene.add_mesh_trimesh(name, shown.mesh, position=shown.position)
        self.nodes[name] = node
        for each in self.nodes.values():  # a drape hides the mosaic under it, and back
            self.style(each)

    def drop(self, name: str) -> None:
        node = self.nodes.pop(name, None)
        if node is not None:
            node.remove()
            for each in self.nodes.values():
                self.style(each)


class Viewer:
    """The viser server and what it shows, each browser in its own view (:class:`ClientView`).

    Parameters
    ----------
    host, port : where to serve; viser takes the next free port if ``port`` is busy, so read
        :attr:`port` for the one it got.
    admit : given the websocket handshake's headers, None to let a browser in, else why not
        (it is closed before anything is sent to it). None: everyone.
    """

    def __init__(
        self,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        admit: Callable[[Any], str | None] | None = None,
    ) -> None:
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port: int = self.server.get_port()
        self.host = host
        self.server.scene.set_up_direction("+z")
        self._lock = threading.RLock()
        self.meshes: dict[str, Shown] = {}  # node name -> what every view shows there
        self.views: dict[int, ClientView] = {}  # client id -> its view
        self.raw: dict[tuple[int, int], str] = {}  # (run, patch index) -> node name
        self.merged: dict[int, str] = {}  # job id -> node name
        self.draped: dict[int, str] = {}  # job id -> its SEM drape's node name
        self.live: dict[int, str] = {}  # run id -> its live mosaic's node name
        self.run_id: int | None = None
        self.zero: float | None = None  # heights are shown relative to the first one
        self.shown_at: dict[str, float] = {}  # node name -> monotonic time it was sent
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        if admit is not None:
            self._guard(admit)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._thread = threading.Thread(target=self._work, name="viewer", daemon=True)
        self._thread.start()

    def _guard(self, admit: Callable[[Any], str | None]) -> None:
        """Close, at the handshake, every websocket ``admit`` refuses: before viser sends
        it anything (its connection callbacks run before the scene is streamed)."""
        sockets = self.server._websock_server

        async def check(client: Any) -> None:
            connection = sockets._live_connections.get(client.client_id)
            if connection is None:
                return
            request = connection.request
            refused = admit(request.headers) if request is not None else "no handshake"
            if refused is not None:
                log.warning("viewer: a browser was refused: %s", refused)
                await connection.close(1008, refused[:120])

        sockets._client_connect_cb.insert(0, check)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    # -- what the server asks (any thread) --------------------------------------------------

    def submit(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def show_patch(self, run_id: int, index: int, hmap: HeightMap, *, patches: int) -> None:
        """A raw patch at its nominal place (its Z as scanned: the drift staircase shows)."""
        with self._lock:
            if self.run_id != run_id:
                for name in self.raw.values():
                    self._drop(name)
                self.raw.clear()
                self.zero = None
                self.run_id = run_id
            if self.zero is None:
                self.zero = float(np.nanmedian(hmap.heights))
            name = f"/raw/run{run_id}/p{index:04d}"
            self._put(name, hmap, max(64, RAW_BUDGET // max(patches, 1)))
            self.raw[(run_id, index)] = name

    def show_mosaic(self, job_id: int, hmap: HeightMap) -> None:
        """A merged mosaic, beside the raw patches; it replaces the previous one (and the live
        mosaic it was merged from)."""
        with self._lock:
            for old in [*self.draped.values(), *self.merged.values(), *self.live.values()]:
                self._drop(old)
            self.draped.clear()
            self.merged.clear()
            self.live.clear()
            name = f"/merged/job{job_id}"
            self._put(name, self._beside(hmap), MERGED_BUDGET)
            self.merged[job_id] = name

    def drape(self, job_id: int, hmap: HeightMap, signal: FloatArray) -> None:
        """The SEM image registered on merged mosaic ``job_id`` (``signal``, on ``hmap``'s
        grid) as its colours: a node in the mosaic's place, shown to the browsers whose
        colour is "SEM"."""
        with self._lock:
            if job_id not in self.merged:
                return  # a newer mosaic replaced it
            name = self.merged[job_id] + DRAPED
            self._put(name, self._beside(hmap), MERGED_BUDGET, tint=signal)
            self.draped[job_id] = name

    def show_live(self, run_id: int, hmap: HeightMap) -> None:
        """A run's live mosaic, beside its raw patches, growing as the run stores patches."""
        with self._lock:
            name = f"/merged/live{run_id}"
            self._put(name, self._beside(hmap), MERGED_BUDGET)
            self.live[run_id] = name

    def _beside(self, hmap: HeightMap) -> HeightMap:
        """``hmap`` moved beside the raw patches (to their right), so "both" compares them."""
        if self.zero is None:
            self.zero = float(np.nanmedian(hmap.heights))
        width = hmap.heights.shape[1] * hmap.pixel_size[0]
        return HeightMap(
            hmap.heights, (hmap.origin[0] + width + BESIDE_GAP, hmap.origin[1]), hmap.pixel_size
        )

    def reset_camera(self) -> None:
        """Every browser's camera back to a view of everything shown, from the -y side."""
        for client in self.server.get_clients().values():
            self._aim(client)

    def _aim(self, client: Any) -> None:
        with self._lock:
            places = [m.position for m in self.meshes.values()]
        xs = [p[0] for p in places] or [0.0]
        ys = [p[1] for p in places] or [0.0]
        centre = np.array([np.mean(xs), np.mean(ys), 0.0])
        span = max(max(xs) - min(xs), max(ys) - min(ys), 2.0)
        # position first: viser moves the look-at point along with a new position
        client.camera.position = tuple(centre + np.array([0.0, -1.2 * span, 1.2 * span]))
        client.camera.look_at = tuple(centre)
        client.camera.up_direction = (0.0, 0.0, 1.0)

    def node_names(self) -> dict[str, list[str]]:
        """Names of the nodes shown: ``{"raw": [...], "merged": [...], "live": [...]}``."""
        with self._lock:
            return {
                "raw": sorted(self.raw.values()),
                "merged": sorted(self.merged.values()),
                "draped": sorted(self.draped.values()),
                "live": sorted(self.live.values()),
            }

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Block until every submitted job is done (tests, benchmarks)."""
        done = threading.Event()
        self._jobs.put(done.set)
        return done.wait(timeout)

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join(10)
        self.server.stop()

    # -- internals --------------------------------------------------------------------------

    def _connect(self, client: Any) -> None:
        """A new browser: its own controls and its own nodes of every mesh, its camera on
        the mosaic."""
        with self._lock:
            view = ClientView(client, self._aim)
            self.views[client.client_id] = view
            for name, shown in self.meshes.items():
                view.put(name, shown)
        self._aim(client)

    def _disconnect(self, client: Any) -> None:
        with self._lock:
            self.views.pop(client.client_id, None)

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except Exception:  # the viewer must never take the server down
                log.exception("viewer update failed")

    def _put(
        self, name: str, hmap: HeightMap, budget: int, *, tint: FloatArray | None = None
    ) -> None:
        import trimesh

        verts, faces, colours, origin = mesh_of(
            hmap, budget=budget, zero=self.zero or 0.0, tint=tint
        )
        mesh = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colours, process=False)
        shown = Shown(mesh, (origin[0], origin[1], 0.0))
        self.meshes[name] = shown
        for view in list(self.views.values()):
            view.put(name, shown)
        self.shown_at[name] = time.monotonic()

    def _drop(self, name: str) -> None:
        self.meshes.pop(name, None)
        for view in list(self.views.values()):
            view.drop(name)
