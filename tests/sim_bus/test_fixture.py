"""The docking fixture of the simulated plant (sim.plant.fixture): the
platform starts resting on it with slack cables, the fixture carries its weight, and it
lets go of a platform lifted off it."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import ConfigError, Robot
from sim_bus.config import parse_sim
from sim_bus.plant import Plant, PlantConfig
from tests.daemon_stack import CONFIGS

ROBOT = Robot.from_yaml(CONFIGS / "robots" / "reference8.yaml")
SLACK = [0.0, 0.06, 0.02, 0.05, 0.01, 0.03, 0.04, 0.06]


def fixture_plant(**fixture: object) -> Plant:
    return Plant(ROBOT, PlantConfig.model_validate({"fixture": {"slack_m": SLACK, **fixture}}))


def test_the_platform_rests_on_the_fixture_its_cables_slack_by_slack_m() -> None:
    plant = fixture_plant()
    taut = ROBOT.cable_lengths(ROBOT.home)
    np.testing.assert_allclose(plant.drum_lengths - taut, SLACK, atol=1e-9)
    start = plant.pose.position.copy()
    for _ in range(1000):  # 1 s, nothing commanded: the fixture carries the weight
        plant.step()
        tensions = plant.tensions
        assert tensions[1:].max() == 0.0  # slack
        assert tensions[0] < 5.0  # just taut: stretched by the platform sinking 0.1 mm
    assert np.linalg.norm(plant.pose.position - start) < 1e-5
    assert np.linalg.norm(plant.pose.position - ROBOT.home.position) < 2e-4  # sunk < 0.2 mm
    unset = Plant(ROBOT, PlantConfig())  # no fixture: at home in equilibrium, as before
    assert unset.tensions.min() > 0.0 and unset.pose == ROBOT.home


def test_a_platform_lifted_off_the_fixture_is_free() -> None:
    """Unilateral: a wrench lifting the platform (more than its weight, and sideways)
    moves it as a free body; the fixture does not hold it down or sideways."""
    lift = (20.0, 0.0, 2.0 * 9.81 * ROBOT.platform.mass, 0.0, 0.0, 0.0)
    plant = Plant(
        ROBOT,
        PlantConfig.model_validate(
            {"fixture": {"slack_m": 0.3}, "disturbance": {"wrench": list(lift)}}
        ),
    )
    start = plant.pose.position.copy()
    plant.advance(0.1)
    moved = plant.pose.position - start
    # free: z'' = g (2 m g up, m g down), x'' = 20 N / m, over 0.1 s
    assert moved[2] == pytest.approx(0.5 * 9.81 * 0.01, rel=0.05)
    assert moved[0] == pytest.approx(0.5 * 20.0 / ROBOT.platform.mass * 0.01, rel=0.05)


def test_a_fixture_at_an_unknown_pose_or_with_a_wrong_slack_count_is_named() -> None:
    with pytest.raises(ConfigError, match=r"sim\.plant\.fixture\.pose: no pose 'dock'"):
        fixture_plant(pose="dock")
    with pytest.raises(ConfigError, match=r"sim\.plant\.fixture\.slack_m: 3 entries for 8"):
        Plant(ROBOT, PlantConfig.model_validate({"fixture": {"slack_m": [0.1, 0.1, 0.1]}}))
    with pytest.raises(ConfigError, match=r"sim\.plant\.fixture\.slack_m"):
        parse_sim({"plant": {"fixture": {"slack_m": -0.1}}})
