"""The simulated Nanonis coarse motors: steps, the stage's closed loop, refusals on the wire."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from hardware.nanonis import wire
from hardware.sim.instrument import SimulatedAFM
from hardware.sim.nanonis_controller import NanonisController
from hardware.sim.nanonis_motor import MotorModule
from hardware.sim.surfaces import Chessboard


@pytest.fixture
def afm() -> Iterator[SimulatedAFM]:
    with SimulatedAFM(Chessboard(seed=1), seed=1) as world:
        yield world


def test_open_loop_steps_move_the_stage_and_the_robot_as_directed(afm: SimulatedAFM) -> None:
    motor = MotorModule(afm)
    x0, y0, z0 = motor.position()
    motor.start_move([0, 50, 0, 1])  # X+
    x1, y1, z1 = motor.position()
    assert x1 > x0 + 1e-7 and abs(y1 - y0) < 1e-8 and abs(z1 - z0) < 1e-8
    motor.start_move([1, 50, 0, 1])  # X- as many: about back (stick-slip steps are not exact)
    assert abs(motor.position()[0] - x0) < 0.2 * (x1 - x0)
    motor.start_move([5, 20, 0, 1])  # Z+ retracts the robot
    assert motor.position()[2] > z0


def test_the_closed_loop_brings_the_stage_to_its_sensors_target(afm: SimulatedAFM) -> None:
    motor = MotorModule(afm)
    motor.closed_loop([1, 2e-6, -1e-6, 0, 0, 0])
    x, y, _ = motor.position()
    assert x == pytest.approx(2e-6, abs=5e-9) and y == pytest.approx(-1e-6, abs=5e-9)
    motor.closed_loop([0, 1e-6, 0.0, 0, 0, 0])  # relative
    assert motor.position()[0] == pytest.approx(3e-6, abs=5e-9)


@pytest.mark.parametrize(
    ("command", "types", "args", "said"),
    [
        ("Motor.StartMove", "IHII", [6, 10, 0, 1], "direction 6 is not in 0..5"),
        ("Motor.StartClosedLoop", "IdddII", [2, 0.0, 0.0, 0.0, 0, 0], "must be 0 or 1"),
    ],
)
def test_bad_motor_arguments_come_back_in_the_error_block(
    afm: SimulatedAFM, command: str, types: str, args: list[object], said: str
) -> None:
    controller = NanonisController(afm)
    try:
        reply = controller.handle(command, wire.encode(types, args))
    finally:
        controller.close()
    header = wire.decode_header(reply[: wire.HEADER_SIZE])
    assert header.command == command
    _, status, description = wire.decode_response((), reply[wire.HEADER_SIZE :], command=command)
    assert status == 1 and said in description
