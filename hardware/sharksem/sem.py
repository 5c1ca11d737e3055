"""The SEM role on a TESCAN microscope, over SharkSEM (:mod:`hardware.sharksem.client`).

An image is acquired as SharkSEM does it: the field of view set (``SetViewField``, mm on the
wire), a detector selected and enabled on an input channel (``DtSelect``, ``DtEnable``), a
frame started (``ScScanXY``: frame id, size, the scanned rectangle, single frame, dwell in
ns), its pixels collected from the ``ScData`` messages on the data link, the scan stopped
(``ScStopScan``). The frame carries its geometry as the SEM reports it: pixel size (the field
over the pixels), scan rotation (the geometry named ``Rotation``, degrees), and the SEM stage
position it was taken at (``StgGetPosition``, mm and degrees). A frame that comes short, out
of order, or not at all is an error and nothing of it is kept.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from hardware.protocols import SEMFrame
from hardware.sharksem.client import PORT, SharkSEMClient
from hardware.sharksem.errors import SharkSEMError, SharkSEMProtocolError
from hardware.sharksem.wire import decode

FloatArray = NDArray[np.float64]

MM = 1e-3
#: The input channel images are taken on.
CHANNEL = 0


def _listing(text: str, kind: str) -> dict[int, str]:
    """``det.0.name=SE`` lines (``kind`` ``det``) as {index: name}."""
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition("=")
        parts = key.strip().split(".")
        if len(parts) == 3 and parts[0] == kind and parts[2] == "name" and parts[1].isdigit():
            out[int(parts[1])] = value.strip()
    return out


class TescanSEM:
    """A TESCAN SEM over SharkSEM.

    Parameters
    ----------
    client : SharkSEMClient
        The open link (:meth:`SharkSEMClient.open`).
    """

    def __init__(
        self, client: SharkSEMClient, *, reopen: Callable[[], SharkSEMClient] | None = None
    ) -> None:
        self._client = client
        self._reopen = reopen
        self._frames = 0
        self._frame_lock = threading.Lock()  # one frame at a time: its commands in order

    @classmethod
    def connect(cls, host: str, port: int = PORT, *, timeout: float = 10.0) -> TescanSEM:
        """Open both links to the SEM at ``host:port``; a link that breaks later is opened
        again at the next request (the SEM's software restarted, a cable put back)."""

        def reopen() -> SharkSEMClient:
            return SharkSEMClient.open(host, port, timeout=timeout)

        return cls(reopen(), reopen=reopen)

    @property
    def client(self) -> SharkSEMClient:
        """The link, opened again if it broke and this SEM knows where it is."""
        if self._client.broken is not None and self._reopen is not None:
            self._client = self._reopen()
        return self._client

    def close(self) -> None:
        self._client.close()

    def version(self) -> str:
        return str(self.client.call("TcpGetVersion", reply="s")[0])

    def view_field(self) -> float:
        """The field of view across, metres."""
        return float(self.client.call("GetViewField", reply="f")[0]) * MM

    def set_view_field(self, field: float) -> None:
        if not (math.isfinite(field) and field > 0):
            raise ValueError(f"the field of view must be a positive length, got {field!r} m")
        self.client.call("SetViewField", "f", [field / MM])

    def stage_position(self) -> tuple[float, float, float, float, float]:
        """The SEM stage: x, y, z (metres), rotation and tilt (degrees)."""
        x, y, z, rot, tilt = self.client.call("StgGetPosition", reply="fffff")
        return x * MM, y * MM, z * MM, rot, tilt

    def detectors(self) -> dict[int, str]:
        """The detectors by index (``DtEnumDetectors``)."""
        return _listing(str(self.client.call("DtEnumDetectors", reply="s")[0]), "det")

    def scan_rotation(self) -> float:
        """The scan rotation, degrees: the geometry named ``Rotation`` (0 when none)."""
        geometries = _listing(str(self.client.call("EnumGeometries", reply="s")[0]), "geom")
        index = next((k for k, name in geometries.items() if name.lower() == "rotation"), None)
        if index is None:
            return 0.0
        angle, _ = self.client.call("GetGeometry", "i", [index], reply="ff")
        return float(angle)

    def acquire(
        self,
        *,
        field: float,
        pixels: int,
        dwell: float = 1e-6,
        detector: str = "SE",
    ) -> SEMFrame:
        """One ``pixels`` x ``pixels`` frame of ``field`` metres across, ``dwell`` seconds a
        pixel, on ``detector``; its geometry as the SEM reports it."""
        with self._frame_lock:
            return self._acquire(field=field, pixels=pixels, dwell=dwell, detector=detector)

    def _acquire(self, *, field: float, pixels: int, dwell: float, detector: str) -> SEMFrame:
        if not 8 <= pixels <= 8192:
            raise ValueError(f"pixels must be in 8..8192, got {pixels}")
        if not (math.isfinite(dwell) and 1e-8 <= dwell <= 1e-3):
            raise ValueError(f"dwell must be 10 ns to 1 ms a pixel, got {dwell!r} s")
        found = self.detectors()
        index = next((k for k, name in found.items() if name.lower() == detector.lower()), None)
        if index is None:
            names = ", ".join(found.values()) or "none"
            raise SharkSEMError(f"the SEM has no detector {detector!r}; it has: {names}")
        self.set_view_field(field)
        self.client.call("DtSelect", "ii", [CHANNEL, index])
        self.client.call("DtEnable", "iii", [CHANNEL, 1, 8])
        rotation = self.scan_rotation()
        x, y, z, _, _ = self.stage_position()
        self._frames += 1
        frame_id = self._frames
        right = bottom = pixels - 1
        started = self.client.call(
            "ScScanXY",
            "IIIIIIIiI",
            [frame_id, pixels, pixels, 0, 0, right, bottom, 1, round(dwell * 1e9)],
            reply="i",
        )[0]
        if started != 0:
            raise SharkSEMError(f"ScScanXY refused the frame (code {started})")
        try:
            image = self._collect(frame_id, pixels * pixels)
        except SharkSEMError as exc:
            link = self._client  # as it is: not opened again here
            if link.broken is None:  # the beam stopped, then the data link given up:
                with contextlib.suppress(SharkSEMError):  # what follows is out of step
                    link.call("ScStopScan")
                link.fail(f"frame {frame_id}: {exc}")
            raise
        self.client.call("ScStopScan")
        return SEMFrame(
            pixels=image.reshape(pixels, pixels).astype(np.float64),
            pixel_size=field / pixels,
            rotation=rotation,
            stage=(x, y, z),
            field=field,
            dwell=dwell,
            detector=found[index],
        )

    def _collect(self, frame_id: int, count: int) -> NDArray[np.uint8]:
        """The frame's pixels from its ``ScData`` messages, in order, all of them."""
        out = np.empty(count, dtype=np.uint8)
        got = 0
        while got < count:
            header, body = self.client.receive_data(f"frame {frame_id} ({got} of {count} px)")
            if header.command != "ScData":
                raise SharkSEMProtocolError(f"the data link sent {header.command!r}, not ScData")
            frame, channel, index, bpp, data = decode("IIIIb", body, what="ScData")
            if frame != frame_id or channel != CHANNEL:
                raise SharkSEMProtocolError(
                    f"ScData of frame {frame} channel {channel} during frame {frame_id}"
                )
            if bpp != 8 or index != got or got + len(data) > count:
                raise SharkSEMProtocolError(
                    f"ScData block at pixel {index} ({len(data)} px, {bpp} bits) does not "
                    f"follow the {got} pixels received of {count}"
                )
            out[got : got + len(data)] = np.frombuffer(data, dtype=np.uint8)
            got += len(data)
        return out
