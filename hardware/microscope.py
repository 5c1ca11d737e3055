"""The instrument the backend works with, opened from one configuration string.

* ``sim://`` — the simulated AFM-in-SEM. Options as a query: ``surface`` (folded, the default:
  structure everywhere on 20.48 x 20.48 µm around the origin before its fields repeat;
  chessboard, a TGX1-like grating; image), ``seed``, ``speed`` (simulated seconds per wall
  second, or ``max``), and for an image ``image`` (a 2-D ``.npy`` of heights in metres) with
  ``pixel`` (``dx,dy`` metres), e.g. ``sim://?surface=folded&seed=3&speed=max``.
* ``mcs://stage=URL;robot=URL`` — real SmarAct MCS controllers on pyserial URLs (device paths,
  ``socket://``, ``rfc2217://``) for the sample stage and the probe robot. The stages move;
  landing and scanning also need an AFM controller, and say so when asked.
* ``nanonis://HOST:PORT?stage=mcs:URL`` — a Nanonis controller over its TCP interface for the
  probe signal (PLL), the force loop (Z controller), the Z and scan piezos and the patch scan,
  with a SmarAct MCS sample stage on a pyserial URL; ``nanonis://HOST:PORT`` alone drives the
  sample stage through Nanonis's coarse motor module too. Options (see
  :func:`hardware.nanonis.open.open_nanonis`): ``landing`` (woodpecker or auto), ``approach``
  (Z- or Z+), ``z_channel``, ``angle``, ``backward_ratio``, ``timeout``, ``motor_group``.
* The SEM composes with either: ``&sem=sharksem://HOST:PORT`` (``;sem=...`` in ``mcs://``), a
  TESCAN SEM over SharkSEM (:mod:`hardware.sharksem.open`); ``sim://`` keeps its own SEM.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit

from hardware.envelope import ScanEnvelope
from hardware.mcs_axis import STAGE_TRAVEL, MCSAxis
from hardware.procedures import LandingReport, land
from hardware.protocols import SEM, ForceLoop, PatchScanner, PositionerAxis, ProbeSignal
from hardware.raster import FineRaster
from hardware.smaract_mcs import MCSController

if TYPE_CHECKING:
    from hardware.sim.instrument import SimulatedAFM
    from hardware.sim.sem import SEMGeometry


#: Side of the default simulated sample (metres): its structure does not repeat within it.
SIM_SAMPLE_SIZE = 20e-6


class ConfigurationError(ValueError):
    """The instrument configuration string is wrong; the message says how to fix it."""


@dataclass
class Microscope:
    """Every hardware role of the AFM-in-SEM; roles a configuration lacks are None."""

    description: str
    stage_x: PositionerAxis
    stage_y: PositionerAxis
    robot_x: PositionerAxis
    robot_y: PositionerAxis
    robot_z: PositionerAxis
    probe: ProbeSignal | None
    loop: ForceLoop | None
    scanner: PatchScanner | None
    sem: SEM | None
    simulated: bool
    #: the simulated world, for its truth and fault injection (None on real hardware)
    sim: SimulatedAFM | None = None
    #: the controller's own landing (Nanonis auto-approach); None: the woodpecker landing
    approach: Callable[[], LandingReport] | None = None
    #: the scan envelope of real hardware (:meth:`scan_envelope`)
    envelope: ScanEnvelope = field(default_factory=ScanEnvelope)
    _closers: tuple[object, ...] = ()

    def require_afm(self) -> tuple[ProbeSignal, ForceLoop, PatchScanner]:
        """The probe, force loop and patch scanner, or a clear error where there are none."""
        if self.probe is None or self.loop is None or self.scanner is None:
            raise ConfigurationError(
                f"{self.description}: no AFM controller (probe signal and force loop) is "
                "configured, so it cannot land or scan; use sim://, nanonis://HOST:PORT?stage="
                "mcs:URL, or add the controller"
            )
        return self.probe, self.loop, self.scanner

    def scan_envelope(self) -> ScanEnvelope:
        """What a scan may ask of the instrument on its sample: the simulator measures its
        own; real hardware takes :attr:`envelope` (defaults for a steep grating on a kHz
        loop, set from the configuration)."""
        if self.sim is not None:
            return self.sim.scan_envelope()
        return self.envelope

    def land(self) -> LandingReport:
        """Bring the tip to the surface: the controller's approach, or the woodpecker landing
        on the robot's Z."""
        probe, loop, _ = self.require_afm()
        if self.approach is not None:
            return self.approach()
        return land(self.robot_z, loop, probe)

    def close(self) -> None:
        """Close every link and simulator this instrument opened."""
        for thing in self._closers:
            close = getattr(thing, "close", None)
            if callable(close):
                close()


def open_microscope(config: str) -> Microscope:
    """Open the instrument described by ``config`` (see the module notes)."""
    parts = urlsplit(config)
    if parts.scheme == "sim":
        return _open_sim(config, parse_qs(parts.query))
    if parts.scheme == "mcs":
        return _open_mcs(config, config[len("mcs://") :])
    if parts.scheme == "nanonis":
        from hardware.nanonis.open import open_nanonis

        return open_nanonis(config)
    raise ConfigurationError(
        f"unknown instrument {config!r}: use sim://?surface=chessboard, "
        "mcs://stage=URL;robot=URL or nanonis://HOST:PORT?stage=mcs:URL"
    )


def _open_sim(config: str, query: dict[str, list[str]]) -> Microscope:
    from hardware.sim.sem import SimulatedSEM

    afm = simulated_afm(config, query)
    return Microscope(
        description=config,
        stage_x=afm.stage_x,
        stage_y=afm.stage_y,
        robot_x=afm.robot_x,
        robot_y=afm.robot_y,
        robot_z=afm.robot_z,
        probe=afm,
        loop=afm,
        scanner=FineRaster(afm.robot_x, afm.robot_y, afm, afm),
        sem=SimulatedSEM(
            afm.surface,
            seed=int(query.get("seed", ["0"])[-1]),
            geometry=_sem_geometry(config, query),
            stage=afm.stage_position,
            sensor_scale=afm.stage_sensor_scale,
        ),
        simulated=True,
        sim=afm,
        _closers=(afm,),
    )


def _sem_geometry(config: str, query: dict[str, list[str]]) -> SEMGeometry:
    """The simulated SEM's scan against the stage: ``sem_rotation`` (degrees, default 3) and
    ``sem_scale`` (default 1.025), so that every run meets an SEM a calibration must find."""
    from hardware.sim.sem import SEMGeometry

    try:
        rotation = float(query.get("sem_rotation", ["3"])[-1])
        scale = float(query.get("sem_scale", ["1.025"])[-1])
    except ValueError:
        raise ConfigurationError(f"{config}: sem_rotation and sem_scale are numbers") from None
    if not (math.isfinite(rotation) and -180 <= rotation <= 180 and 0.5 <= scale <= 2.0):
        raise ConfigurationError(
            f"{config}: sem_rotation must be in -180..180 degrees and sem_scale in 0.5..2"
        )
    return SEMGeometry(rotation=rotation, scale=scale)


def simulated_afm(
    config: str,
    query: dict[str, list[str]] | None = None,
    *,
    host: str = "127.0.0.1",
    stage_port: int = 0,
) -> SimulatedAFM:
    """The simulated world a ``sim://`` string describes (its sample stage's MCS server on
    ``host:stage_port``); :class:`ConfigurationError` for a wrong option."""
    from hardware.sim.clock import SimClock
    from hardware.sim.instrument import SimulatedAFM
    from hardware.sim.surfaces import surface_by_name

    if query is None:
        query = parse_qs(urlsplit(config).query)

    known = {"surface", "seed", "speed", "image", "pixel", "sem_rotation", "sem_scale"}
    unknown = set(query) - known
    if unknown:
        raise ConfigurationError(
            f"{config}: unknown option(s) {sorted(unknown)}; use {sorted(known)}"
        )
    name = query.get("surface", ["folded"])[-1]
    try:
        seed = int(query.get("seed", ["0"])[-1])
    except ValueError:
        raise ConfigurationError(f"{config}: seed must be an integer") from None
    speed_text = query.get("speed", ["max"])[-1]
    try:
        speed = None if speed_text == "max" else float(speed_text)
        clock = SimClock(speed)
    except ValueError:
        raise ConfigurationError(
            f"{config}: speed must be 'max' or a positive number of simulated s per s"
        ) from None
    pixel = None
    if "pixel" in query:
        try:
            px, py = (float(v) for v in query["pixel"][-1].split(","))
        except ValueError:
            raise ConfigurationError(f"{config}: pixel must be DX,DY in metres") from None
        pixel = (px, py)
    try:
        surface = surface_by_name(
            name,
            seed=seed,
            image=query.get("image", [None])[-1],
            pixel=pixel,
            centred=True,
            size=SIM_SAMPLE_SIZE,
        )
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"{config}: {exc}") from None
    return SimulatedAFM(surface, clock=clock, seed=seed, host=host, stage_port=stage_port)


def _open_mcs(config: str, spec: str) -> Microscope:
    urls: dict[str, str] = {}
    for item in filter(None, spec.split(";")):
        key, sep, value = item.partition("=")
        if not sep or key not in ("stage", "robot", "sem") or not value:
            raise ConfigurationError(
                f"{config}: expected stage=URL;robot=URL[;sem=sharksem://HOST:PORT], got {item!r}"
            )
        urls[key] = value
    if not {"stage", "robot"} <= set(urls):
        raise ConfigurationError(f"{config}: both stage=URL and robot=URL are needed")
    sem = None
    if "sem" in urls:
        from hardware.sharksem.open import SEMConfigurationError, open_sem

        try:
            sem = open_sem(urls["sem"])
        except SEMConfigurationError as exc:
            raise ConfigurationError(f"{config}: {exc}") from None
    opened: list[Any] = [sem] if sem is not None else []
    try:
        stage = MCSController.open(urls["stage"])
        opened.append(stage)
        robot = MCSController.open(urls["robot"])
        opened.append(robot)
    except Exception:
        for thing in opened:
            thing.close()
        raise
    return Microscope(
        description=config,
        stage_x=MCSAxis(stage, 0, name="stage x", travel=STAGE_TRAVEL),
        stage_y=MCSAxis(stage, 1, name="stage y", travel=STAGE_TRAVEL),
        robot_x=MCSAxis(robot, 0, name="robot x"),
        robot_y=MCSAxis(robot, 1, name="robot y"),
        robot_z=MCSAxis(robot, 2, name="robot z"),
        probe=None,
        loop=None,
        scanner=None,
        sem=sem,
        simulated=False,
        _closers=tuple(opened),
    )
