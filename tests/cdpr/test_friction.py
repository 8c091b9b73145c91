"""The winches' Coulomb friction from the robot file (cdpr.friction): the force the
controller adds along the reference's cable rates, and what it buys on a plant whose
drums have it (the simulator's sim.plant.friction, a sticking drum model of its own)."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from cdpr.friction import SPEED_FLOOR
from sim_bus.plant.config import parse_plant_config
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking

FRICTION = 2.0  # N, the winch


def _with_friction(robot: Robot, friction: float, **cables: float) -> Robot:
    data = robot.spec.model_dump(exclude_none=True)
    data["actuator"]["friction"] = friction
    for k, value in cables.items():
        data["cables"][int(k[1:])]["actuator"] = {"friction": value}
    return Robot.from_dict(data)


def test_the_drag_is_the_back_emf_and_the_friction_against_the_motion(
    reference8: Robot,
) -> None:
    """k0 l' plus F tanh(l' / SPEED_FLOOR) per cable (cable 3's own friction): the full
    friction against a drum moving well above the floor, none at rest; without friction
    in the file exactly k0 l'."""
    robot = _with_friction(reference8, FRICTION, c3=5.0)
    rates = np.array([0.1, -0.1, 0.0, 0.1, SPEED_FLOOR, -1e-6, 0.2, -0.3])
    friction = np.full(8, FRICTION)
    friction[3] = 5.0
    expected = robot.k0 * rates + friction * np.tanh(rates / SPEED_FLOOR)
    np.testing.assert_allclose(robot.drag(rates), expected, rtol=0, atol=1e-12)
    assert robot.drag(rates)[0] == pytest.approx(robot.k0[0] * 0.1 + FRICTION, rel=1e-6)
    assert robot.drag(rates)[2] == 0.0
    np.testing.assert_array_equal(reference8.drag(rates), reference8.k0 * rates)


@pytest.mark.slow  # six lock-step flights, ~10 s
@pytest.mark.parametrize(
    ("scenario", "within"), [("figure_eight", 0.2), ("vertical_lift", 0.25), ("edge_move", 0.2)]
)
def test_friction_in_the_robot_file_is_compensated_in_flight(
    reference8: Robot, scenario: str, within: float
) -> None:
    """Drums with 2 N of Coulomb friction: with it in the robot file the standard flights
    track within 0.2-0.25 mm RMS, and the figure-eight and the edge move at least 2.5x
    better than with the file silent about it (measured 0.12 / 0.17 / 0.10 mm against
    0.75 / 0.23 / 0.39 mm: the integral action chases each reversal, and the payload
    estimate reads the unexplained force as inertia; at 5 N the figure-eight without it
    faulted on an inertia beyond its limits)."""
    plant = parse_plant_config({"friction": {"coulomb": FRICTION}})
    rms = {}
    for label, robot in (("with", _with_friction(reference8, FRICTION)), ("without", reference8)):
        trajectory = STANDARD_SET[scenario](reference8)
        run = run_tracking(robot, trajectory, ParallelController(robot, ControllerSpec()), plant)
        assert run.fault == "", (label, run.fault)
        rms[label] = run.rms_mm
    assert rms["with"] < within, rms
    if scenario != "vertical_lift":  # a lift reverses no cable: little to gain
        assert rms["with"] < rms["without"] / 2.5, rms
