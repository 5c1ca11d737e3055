"""``nanonis://HOST:PORT?...``: a microscope whose AFM controller is a Nanonis.

Options (query, every one checked at start-up):

==================  ==========================================================================
``stage``           ``mcs:URL``: the sample stage is a SmarAct MCS controller on a pyserial URL
                    (channels 0 and 1 are X and Y). Absent: Nanonis's coarse motor module moves
                    the stage (closed loop, so its motors need sensors).
``landing``         ``woodpecker`` (default: the project's landing on the Z piezo and the Z
                    motor) or ``auto`` (the controller's own auto-approach).
``approach``        the Z motor direction towards the sample, ``Z-`` (default) or ``Z+``.
``z_channel``       the signal slot of Z in the scan buffer (default 14).
``angle``           scan frame angle, degrees clockwise (default 0).
``backward_ratio``  backward over forward scan speed (default 1).
``timeout``         seconds to wait for a response (default 5).
``motor_group``     the coarse motor module's group (default 0).
``sem``             ``sharksem://HOST:PORT``: a TESCAN SEM over SharkSEM
                    (:mod:`hardware.sharksem.open`). Absent: no SEM (images are uploaded).
==================  ==========================================================================
"""

from __future__ import annotations

from urllib.parse import parse_qs, urlsplit

from hardware.mcs_axis import STAGE_TRAVEL, MCSAxis
from hardware.microscope import ConfigurationError, Microscope
from hardware.nanonis.client import NanonisClient
from hardware.nanonis.errors import NanonisError
from hardware.nanonis.roles import (
    NanonisMotorAxis,
    NanonisProbe,
    NanonisScanAxis,
    NanonisZAxis,
    NanonisZLoop,
    ZPiezo,
    auto_approach,
)
from hardware.nanonis.scanner import NanonisScanner
from hardware.protocols import PositionerAxis
from hardware.sharksem.open import SEMConfigurationError, open_sem
from hardware.sharksem.sem import TescanSEM
from hardware.smaract_errors import MCSError
from hardware.smaract_mcs import MCSController

OPTIONS = (
    "stage",
    "landing",
    "approach",
    "z_channel",
    "angle",
    "backward_ratio",
    "timeout",
    "motor_group",
    "sem",
)


def _number(config: str, query: dict[str, str], key: str, default: float) -> float:
    try:
        return float(query.get(key, default))
    except ValueError:
        raise ConfigurationError(f"{config}: {key} must be a number, got {query[key]!r}") from None


def open_nanonis(config: str) -> Microscope:
    """Connect to the Nanonis (and the MCS stage) that ``config`` names; every mistake in it
    is a :class:`ConfigurationError` that says what to write instead."""
    parts = urlsplit(config)
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        port = None
    if not host or port is None:
        raise ConfigurationError(
            f"{config}: give the controller's address, nanonis://HOST:PORT (the TCP port "
            "opened in Nanonis's TCP programming interface options, 6501 by default)"
        )
    raw = parse_qs(parts.query)
    unknown = set(raw) - set(OPTIONS)
    if unknown:
        raise ConfigurationError(f"{config}: unknown option(s) {sorted(unknown)}; use {OPTIONS}")
    query = {k: v[-1] for k, v in raw.items()}
    landing = query.get("landing", "woodpecker")
    if landing not in ("woodpecker", "auto"):
        raise ConfigurationError(f"{config}: landing must be woodpecker or auto, got {landing!r}")
    approach = query.get("approach", "Z-")
    if approach not in ("Z-", "Z+"):
        raise ConfigurationError(f"{config}: approach must be Z- or Z+, got {approach!r}")
    stage_url = query.get("stage")
    if stage_url is not None and not (stage_url.startswith("mcs:") and len(stage_url) > 4):
        raise ConfigurationError(
            f"{config}: stage must be mcs:URL (e.g. stage=mcs:socket://HOST:PORT or "
            f"stage=mcs:/dev/ttyUSB0), got {stage_url!r}"
        )
    timeout = _number(config, query, "timeout", 5.0)
    ratio = _number(config, query, "backward_ratio", 1.0)
    angle = _number(config, query, "angle", 0.0)
    z_channel, group = (
        _number(config, query, k, d) for k, d in (("z_channel", 14), ("motor_group", 0))
    )
    if not timeout > 0 or not ratio > 0 or z_channel != int(z_channel) or group != int(group):
        raise ConfigurationError(
            f"{config}: timeout and backward_ratio must be positive, z_channel and "
            "motor_group whole numbers"
        )

    stage: MCSController | None = None
    sem: TescanSEM | None = None
    if "sem" in query:
        try:
            sem = open_sem(query["sem"])
        except SEMConfigurationError as exc:
            raise ConfigurationError(f"{config}: {exc}") from None
    try:
        client = NanonisClient.open(host, port, timeout=timeout)
    except NanonisError as exc:
        if sem is not None:
            sem.close()
        raise ConfigurationError(f"{config}: {exc}") from None
    try:
        high, low = client.z_limits()
        z = ZPiezo(high, low)
        probe = NanonisProbe(client)
        loop = NanonisZLoop(client, z)
        scanner = NanonisScanner(
            client, z, probe, z_channel=int(z_channel), angle=angle, backward_ratio=ratio
        )
        rx, ry = scanner.fine_range
        stage_x: PositionerAxis
        stage_y: PositionerAxis
        if stage_url is not None:
            stage = MCSController.open(stage_url[len("mcs:") :])
            stage_x, stage_y = (
                MCSAxis(stage, 0, name="stage x", travel=STAGE_TRAVEL),
                MCSAxis(stage, 1, name="stage y", travel=STAGE_TRAVEL),
            )
        else:
            stage_x = NanonisMotorAxis(client, 0, group=int(group))
            stage_y = NanonisMotorAxis(client, 1, group=int(group))
    except (NanonisError, MCSError) as exc:
        client.close()
        if sem is not None:
            sem.close()
        raise ConfigurationError(f"{config}: {exc}") from None
    return Microscope(
        description=config,
        stage_x=stage_x,
        stage_y=stage_y,
        robot_x=NanonisScanAxis(client, 0, rx),
        robot_y=NanonisScanAxis(client, 1, ry),
        robot_z=NanonisZAxis(client, z, approach=approach, group=int(group)),
        probe=probe,
        loop=loop,
        scanner=scanner,
        sem=sem,
        simulated=False,
        approach=(lambda: auto_approach(client, loop, probe)) if landing == "auto" else None,
        _closers=tuple(c for c in (client, stage, sem) if c is not None),
    )
