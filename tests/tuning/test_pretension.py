"""Pretension in lock-step (cdpr.pretension through tuning.pretension):
from slack cables on a docking fixture to the position loop, on a simulated robot that
is not the robot file; each abort names its reason.  Simulated time: deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from cdpr.controller import ParallelController
from cdpr.pretension import PretensionSpec, ramp_target
from sim_bus.plant import CableConfig, PlantConfig
from tests.daemon_stack import CONFIGS
from tuning.pretension import run_pretension

ROBOT = Robot.from_yaml(CONFIGS / "robots" / "reference8.yaml")
CONTROLLER = ControllerSpec.model_validate({"pid": {"kp": 100.0, "ki": 50.0, "kd": 20.0}})
SLACK = [0.0, 0.06, 0.02, 0.05, 0.01, 0.03, 0.04, 0.06]


def plant(mismatch: dict | None = None, **fixture: object) -> PlantConfig:
    return PlantConfig.model_validate(
        {
            "fixture": {"slack_m": SLACK, **fixture},
            "encoder": {"counts_per_metre": 1e5, "noise_std": 1e-5},
            "mismatch": mismatch or {},
        }
    )


@pytest.mark.parametrize(
    "mismatch",
    [{}, {"mass_scale": 0.9}, {"payload": {"mass": 2.0}}, {"anchor_error_std": 0.01}],
    ids=["exact", "lighter", "heavier", "anchors"],
)
def test_from_slack_cables_to_the_position_loop_without_moving(mismatch: dict) -> None:
    """Taut, ramped and held: the platform moves < 2 mm (true position, from rest to 1 s
    after the fixture's share is handed over), no cable beyond force_max or beyond the
    static tensions it ends at, no step in force when the loop closes."""
    run = run_pretension(ROBOT, plant(mismatch), CONTROLLER)
    assert run.fault == ""
    assert run.motion_mm < 0.5
    # the slackest cable (6 cm at 5 cm/s) is taut last, after its taut_time
    assert 1.2 + PretensionSpec().taut_time < run.taut_seconds < 3.0
    held = ParallelController(ROBOT, CONTROLLER)
    static = held.tension.solve(
        ROBOT.jacobian(ROBOT.home), ROBOT.bias_wrench(ROBOT.home, np.zeros(6)),
        np.zeros(8), np.zeros(8),
    ).tensions  # fmt: skip
    assert run.peak_force_n < ROBOT.force_max.min()
    assert run.peak_force_n < 1.2 * static.max()
    assert run.loop_close_step_n < 3.0  # N, of ~270 N: encoder noise through kd


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_a_cable_stiffness_off_the_file_does_not_look_like_motion(scale: float) -> None:
    """The ramp stretches the cables by the file's EA x 1/scale: the watch fits that
    factor with the motion, so the motion it sees stays near the truth (~0.1 mm)."""
    config = plant().model_copy(update={"cable": CableConfig(stiffness=1e5 * scale)})
    run = run_pretension(ROBOT, config, CONTROLLER)
    assert run.fault == ""
    assert run.motion_mm < 0.5
    assert run.watched_mm < 0.5


def test_a_cable_that_never_gets_taut_aborts_naming_it() -> None:
    """Cable 3 hangs 0.8 m slack (unhooked): winding it in 0.5 m finds no tension."""
    slack = list(SLACK)
    slack[3] = 0.8
    run = run_pretension(ROBOT, plant(slack_m=slack), CONTROLLER)
    assert "cable 3 wound in 0.50" in run.fault
    assert "max_wind_in 0.5 m" in run.fault
    assert np.isnan(run.closed_at)


def test_a_cable_not_taut_within_taut_timeout_aborts_naming_it() -> None:
    spec = PretensionSpec(taut_timeout=1.0)
    run = run_pretension(ROBOT, plant(), CONTROLLER, spec)
    assert "cable(s) 1, 3, 6, 7 not taut after 1.0 s" in run.fault


def test_a_platform_that_lifts_during_the_ramp_aborts_naming_the_motion() -> None:
    """Ramping open loop to the whole weight (carry 1) of a platform 20 % lighter than the
    file lifts it off the fixture at 80 %: the watch stops it at max_motion."""
    spec = PretensionSpec(carry=1.0)
    run = run_pretension(ROBOT, plant({"mass_scale": 0.8}), CONTROLLER, spec)
    assert "the platform moved 2.0" in run.fault
    assert "(max_motion 2 mm) during the tension ramp" in run.fault


def test_the_ramp_ends_at_the_distribution_of_carry_times_the_static_wrench() -> None:
    solver = ParallelController(ROBOT, CONTROLLER).tension
    target = ramp_target(ROBOT, solver, ROBOT.home, 0.8)
    wrench = -ROBOT.jacobian(ROBOT.home).T @ target
    static = ROBOT.bias_wrench(ROBOT.home, np.zeros(6))
    np.testing.assert_allclose(wrench, 0.8 * static, atol=1e-6)  # tau = Lambda^T f, f = -t
    assert target.min() >= ROBOT.t_min.min() - 1e-9
