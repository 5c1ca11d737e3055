from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from hardware.microscope import ConfigurationError, open_microscope
from hardware.protocols import SEM, PatchScanner
from hardware.sim.mcs_device import MCSDevice
from hardware.sim.mcs_server import MCSServer
from hardware.sim.sem import SimulatedSEM
from hardware.sim.surfaces import Chessboard


def test_sim_configuration_gives_every_role() -> None:
    scope = open_microscope("sim://?surface=folded&seed=2&speed=max")
    try:
        assert scope.simulated
        probe, loop, scanner = scope.require_afm()
        assert probe is loop is scope.sim  # the simulated AFM is probe and loop
        assert isinstance(scanner, PatchScanner)  # its fine axes raster the patch
        assert scanner.fine_range == (scope.robot_x.fine_range, scope.robot_y.fine_range)
        assert isinstance(scope.sem, SEM)
        scope.stage_x.move_to(1e-6)
        assert scope.stage_x.position() == pytest.approx(1e-6, abs=5e-9)
    finally:
        scope.close()


@pytest.mark.parametrize(
    "config",
    [
        "ftp://x",
        "sim://?surface=mars",
        "sim://?seed=abc",
        "sim://?speed=-2",
        "sim://?colour=red",
        "mcs://stage=socket://127.0.0.1:1",
        "mcs://robot",
        "nanonis://",
        "nanonis://127.0.0.1",
        "nanonis://127.0.0.1:1",
        "nanonis://127.0.0.1:1?landing=jump",
        "nanonis://127.0.0.1:1?stage=socket://x:1",
        "nanonis://127.0.0.1:1?timeout=soon",
        "nanonis://127.0.0.1:1?colour=red",
    ],
)
def test_bad_configurations_say_what_to_fix(config: str) -> None:
    with pytest.raises(ConfigurationError, match=r"\S"):
        open_microscope(config)


def test_mcs_configuration_moves_stages_but_cannot_land() -> None:
    with MCSServer(MCSDevice(channels=2)) as stage, MCSServer(MCSDevice(channels=3)) as robot:
        scope = open_microscope(f"mcs://stage={stage.url};robot={robot.url}")
        try:
            scope.stage_y.move_to(-2e-6)
            assert scope.stage_y.position() == pytest.approx(-2e-6, abs=5e-9)
            with pytest.raises(ConfigurationError, match="cannot land or scan"):
                scope.require_afm()
        finally:
            scope.close()


def test_sem_calibration_maps_a_feature_to_its_stage_position() -> None:
    # one raised square of the chessboard has its centre at (0.75, 0.75) µm
    board = Chessboard(roughness=0.0)
    img = SimulatedSEM(board, noise=0.0).grab(centre=(0.75e-6, 0.75e-6), field=2.5e-6, pixels=200)
    edges = img.pixels > np.percentile(img.pixels, 90)  # tilt contrast: bright edges
    rows, cols = np.nonzero(edges)
    # the bright frame around the centre square, by its extreme pixels
    x, y = img.to_stage(0.5 * (cols.min() + cols.max()), 0.5 * (rows.min() + rows.max()))
    assert x == pytest.approx(0.75e-6, abs=0.05e-6)
    assert y == pytest.approx(0.75e-6, abs=0.05e-6)
    # and the edges are where the heights change: compare with the height gradient
    rows, cols = np.mgrid[0:200, 0:200]
    xx, yy = img.to_stage(0.0, 0.0)[0] + cols * img.map[0, 0], img.origin[1] + rows * img.map[1, 1]
    h = board.height(xx, yy)
    steep = (
        ndimage.gaussian_gradient_magnitude(h, 1)
        > 0.5 * ndimage.gaussian_gradient_magnitude(h, 1).max()
    )
    assert (edges & steep).sum() > 0.5 * edges.sum()


def test_a_real_image_as_the_simulated_sample(tmp_path) -> None:  # type: ignore[no-untyped-def]
    heights = np.random.default_rng(0).normal(0, 5e-9, (64, 64))
    np.save(tmp_path / "img.npy", heights)
    scope = open_microscope(f"sim://?surface=image&image={tmp_path / 'img.npy'}&pixel=2e-8,2e-8")
    try:
        assert scope.sem is not None
        img = scope.sem.grab(centre=(0.0, 0.0), field=1e-6, pixels=32)
        assert np.isfinite(img.pixels).all()
    finally:
        scope.close()
    with pytest.raises(ConfigurationError, match="needs an image file"):
        open_microscope("sim://?surface=image")
