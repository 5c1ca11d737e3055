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
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from backend.formats.exports import grid_triangles
from merge.io.detail import block_means, detail_frame, detail_step
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
    hmap: HeightMap, *, budget: int, zero: float
) -> tuple[NDArray[np.float32], NDArray[np.uint32], NDArray[np.uint8], tuple[float, float]]:
    """Vertices (µm, local to the map's origin; heights relative to ``zero``), triangles
    over finite cells, vertex colours, and the origin (µm) to place the node at."""
    heights, k = decimate(hmap.heights, budget)
    ny, nx = heights.shape
    (ox, oy), (px, py) = detail_frame(hmap.origin, hmap.pixel_size, k)
    dx, dy = px * UM, py * UM
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    finite = np.isfinite(heights)
    fill = np.where(finite, heights, np.nanmin(heights) if finite.any() else 0.0)
    verts = np.stack([jj * dx, ii * dy, (fill - zero) * UM], axis=-1).reshape(-1, 3)
    faces = grid_triangles(finite)
    lo, hi = np.nanpercentile(heights, [1, 99]) if finite.any() else (0.0, 1.0)
    colours = afm_colors((heights - lo) / max(hi - lo, 1e-12)).reshape(-1, 3)
    origin = (ox * UM, oy * UM)
    return verts.astype(np.float32), faces.astype(np.uint32), colours, origin


class Viewer:
    """The viser server and what it shows.

    Parameters
    ----------
    host, port : where to serve; viser takes the next free port if ``port`` is busy, so read
        :attr:`port` for the one it got.
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8080) -> None:
        import viser

        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port: int = self.server.get_port()
        self.host = host
        self.server.scene.set_up_direction("+z")
        self._lock = threading.Lock()
        self.raw: dict[tuple[int, int], Any] = {}  # (run, patch index) -> node
        self.merged: dict[int, Any] = {}  # job id -> node
        self.live: dict[int, Any] = {}  # run id -> its live mosaic's node
        self.run_id: int | None = None
        self.zero: float | None = None  # heights are shown relative to the first one
        self.shown_at: dict[str, float] = {}  # node name -> monotonic time it was sent
        self._jobs: queue.Queue[Callable[[], None] | None] = queue.Queue()
        gui = self.server.gui
        self.exaggeration = gui.add_slider(
            "Z exaggeration", min=1.0, max=200.0, step=1.0, initial_value=1.0
        )
        self.show = gui.add_dropdown("Show", ("both", "raw", "merged"), initial_value="both")
        self.reset = gui.add_button("Reset camera")
        self.exaggeration.on_update(lambda _: self._restyle())
        self.show.on_update(lambda _: self._restyle())
        self.reset.on_click(lambda _: self.reset_camera())
        self.server.on_client_connect(self._aim)  # a new browser starts on the mosaic
        self._thread = threading.Thread(target=self._work, name="viewer", daemon=True)
        self._thread.start()

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
                self._clear_raw()
                self.run_id = run_id
            if self.zero is None:
                self.zero = float(np.nanmedian(hmap.heights))
            name = f"/raw/run{run_id}/p{index:04d}"
            node = self._add(name, hmap, max(64, RAW_BUDGET // max(patches, 1)))
            old = self.raw.pop((run_id, index), None)
            if old is not None:
                old.remove()
            self.raw[(run_id, index)] = node
            self._style(node, merged=False)

    def show_mosaic(self, job_id: int, hmap: HeightMap) -> None:
        """A merged mosaic, beside the raw patches; it replaces the previous one (and the live
        mosaic it was merged from)."""
        with self._lock:
            for old in [*self.merged.values(), *self.live.values()]:
                old.remove()
            self.merged.clear()
            self.live.clear()
            node = self._add(f"/merged/job{job_id}", self._beside(hmap), MERGED_BUDGET)
            self.merged[job_id] = node
            self._style(node, merged=True)

    def show_live(self, run_id: int, hmap: HeightMap) -> None:
        """A run's live mosaic, beside its raw patches, growing as the run stores patches."""
        with self._lock:
            old = self.live.pop(run_id, None)
            if old is not None:
                old.remove()
            node = self._add(f"/merged/live{run_id}", self._beside(hmap), MERGED_BUDGET)
            self.live[run_id] = node
            self._style(node, merged=True)

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
        nodes = [*self.raw.values(), *self.merged.values(), *self.live.values()]
        xs = [float(n.position[0]) for n in nodes] or [0.0]
        ys = [float(n.position[1]) for n in nodes] or [0.0]
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
                "raw": sorted(n.name for n in self.raw.values()),
                "merged": sorted(n.name for n in self.merged.values()),
                "live": sorted(n.name for n in self.live.values()),
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

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                job()
            except Exception:  # the viewer must never take the server down
                log.exception("viewer update failed")

    def _add(self, name: str, hmap: HeightMap, budget: int) -> Any:
        import trimesh

        verts, faces, colours, origin = mesh_of(hmap, budget=budget, zero=self.zero or 0.0)
        mesh = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colours, process=False)
        node = self.server.scene.add_mesh_trimesh(name, mesh, position=(origin[0], origin[1], 0.0))
        self.shown_at[name] = time.monotonic()
        return node

    def _clear_raw(self) -> None:
        for node in self.raw.values():
            node.remove()
        self.raw.clear()
        self.zero = None

    def _style(self, node: Any, *, merged: bool) -> None:
        mode = self.show.value
        node.visible = mode == "both" or mode == ("merged" if merged else "raw")
        node.scale = (1.0, 1.0, float(self.exaggeration.value))

    def _restyle(self) -> None:
        with self._lock:
            for node in self.raw.values():
                self._style(node, merged=False)
            for node in [*self.merged.values(), *self.live.values()]:
                self._style(node, merged=True)
