"""The Nanonis driver against the protocol simulator over real TCP sockets."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from hardware.errors import CrashError, SaturationError
from hardware.microscope import Microscope, open_microscope
from hardware.procedures import move_stage, retract, safe_state, sample_origin
from hardware.protocols import ScanLines
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_server import NanonisServer
from hardware.sim.surfaces import Chessboard

SIZE, PIXELS = (0.8e-6, 0.6e-6), (32, 24)


@pytest.fixture
def server() -> Iterator[NanonisServer]:
    with SimulatedAFM(Chessboard(seed=2), seed=2) as afm, NanonisServer(afm) as srv:
        yield srv


def patch(m: Microscope, origin: tuple[float, float]) -> tuple[ScanLines, tuple[float, float]]:
    """Move, land, scan and retract one patch, as the runner does."""
    _, loop, scanner = m.require_afm()
    move_stage(m.stage_x, m.stage_y, m.robot_x, m.robot_y, origin=origin, size=SIZE)
    scanner.prepare(size=SIZE, pixels=PIXELS)
    m.land()
    try:
        lines = scanner.scan(size=SIZE, pixels=PIXELS, line_rate=2.0)
    finally:
        retract(m.robot_z, loop)
    lines.require_unsaturated()
    nominal = sample_origin(
        lines, m.stage_x, m.stage_y, planned=origin, size=SIZE, x=m.robot_x, y=m.robot_y
    )
    return lines, nominal


def assert_safe(server: NanonisServer) -> None:
    afm = server.afm
    assert not afm.engaged(), "the Z controller is still on"
    assert afm.robot_device.axes[2].extension(afm.clock.now()) == pytest.approx(0.0, abs=1e-9)
    assert not server.controller._busy("scan"), "the scan still runs"


def assert_matches_truth(server: NanonisServer, lines: ScanLines) -> None:
    """The heights are the true surface where the stage truly stood (its sensors read tens
    of nm off: the merge's job), up to Z's offset and the drift's plane, within what the
    piezos' hysteresis and creep leave (a few nm on the grating's edges)."""
    afm = server.afm
    ny, nx = lines.heights.shape
    t = afm.clock.now()
    sx, sy = (axis.true_position(t) for axis in afm.stage_device.axes)
    x0, y0 = lines.origin[0] - sx, lines.origin[1] - sy
    truth = afm.true_heights(x0, y0, (ny, nx), lines.pixel_size[0], tip=True)
    rows, cols = np.mgrid[0:ny, 0:nx]
    basis = np.column_stack([np.ones(rows.size), rows.ravel(), cols.ravel()])
    diff = (lines.heights - truth).ravel()
    error = diff - basis @ np.linalg.lstsq(basis, diff, rcond=None)[0]
    assert np.median(np.abs(error)) < 6e-9 < np.ptp(truth)


@pytest.mark.parametrize(
    "options",
    ["&timeout=2", "&landing=auto&timeout=2", "motors"],
    ids=["woodpecker", "auto", "motors"],
)
def test_patches_on_the_nanonis_are_the_sample_where_the_stage_put_them(
    server: NanonisServer, options: str
) -> None:
    host, port = server.address
    url = f"nanonis://{host}:{port}" if options == "motors" else server.instrument_url + options
    m = open_microscope(url)
    try:
        for planned in [(-0.5e-6, 0.2e-6), (0.1e-6, 0.2e-6)]:
            lines, origin = patch(m, planned)
            assert lines.heights.shape == (24, 32)
            assert np.hypot(origin[0] - planned[0], origin[1] - planned[1]) < 60e-9
            assert_matches_truth(server, lines)
            assert np.all(np.diff(lines.line_times) > 0)
        assert_safe_after(m, server)
    finally:
        m.close()


def assert_safe_after(m: Microscope, server: NanonisServer) -> None:
    safe_state(m.loop, m.robot_z, (m.stage_x, m.stage_y, m.robot_x, m.robot_y), scanner=m.scanner)
    assert_safe(server)


@pytest.mark.parametrize(
    ("fault", "error", "words"),
    [("pll_loss", CrashError, "PLL lost lock"), ("z_limit", SaturationError, "limit")],
)
def test_a_fault_mid_frame_is_caught_and_ends_safe(
    server: NanonisServer, fault: str, error: type[Exception], words: str
) -> None:
    m = open_microscope(server.instrument_url + "&timeout=2")
    try:
        server.inject_physics(fault, after_lines=6)  # type: ignore[arg-type]
        with pytest.raises(error, match=words):
            patch(m, (0.0, 0.0))
        assert_safe_after(m, server)
        server.inject_physics(None)
        lines, _ = patch(m, (0.0, 0.0))  # healed: the same patch scans
        assert_matches_truth(server, lines)
    finally:
        m.close()


def test_pixels_the_scan_buffer_cannot_take_are_refused_before_landing(
    server: NanonisServer,
) -> None:
    m = open_microscope(server.instrument_url)
    try:
        _, _, scanner = m.require_afm()
        with pytest.raises(Exception, match="multiple of 16"):
            scanner.prepare(size=SIZE, pixels=(30, 24))
        assert not server.afm.engaged()
    finally:
        m.close()


def test_a_dropped_link_is_reopened_for_reads_and_the_safe_state(server: NanonisServer) -> None:
    m = open_microscope(server.instrument_url + "&timeout=1")
    try:
        assert m.probe is not None
        server.inject("drop", count=1)
        assert abs(m.probe.frequency_shift()) < 5  # the read went through on a new link
        server.inject("drop", count=2)
        assert_safe_after(m, server)
    finally:
        m.close()
