"""The simulator's `sim:` section: the wake-up period and its checks, and a daemon that
tracks against a simulator waking every 5 ms (its plant still steps every 1 ms)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cdpr import ConfigError, Pose
from drivers.config import parse_drives
from sim_bus.config import parse_sim
from tests.daemon_stack import Stack, config_for

ODRIVES = parse_drives({"protocol": "odrive", "nodes": [0, 1], "feedback_rate_hz": 500}, "d")
CIA402 = parse_drives({"protocol": "cia402", "nodes": [1, 2], "rated_torque": 2.0}, "d")


def test_wake_defaults_to_the_plant_step() -> None:
    assert parse_sim({"plant": {"step": 0.002}}).wake(CIA402) == 0.002


def test_wake_period_is_used_where_the_drives_allow_it() -> None:
    assert parse_sim({"wake_period": 0.01}).wake(CIA402) == 0.01
    assert parse_sim({"wake_period": 0.002}).wake(ODRIVES) == 0.002


def test_wake_period_below_the_plant_step_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"wake_period.*shorter than plant.step"):
        parse_sim({"wake_period": 0.0005, "plant": {"step": 0.001}})


def test_wake_period_beyond_the_streamed_feedback_interval_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"1 / drives.feedback_rate_hz = 0.002 s"):
        parse_sim({"wake_period": 0.005}).wake(ODRIVES)


@pytest.mark.timeout(60)
def test_a_daemon_tracks_against_a_simulator_waking_every_5_ms() -> None:
    async def scenario() -> None:
        config = config_for("cia402", sim={"wake_period": 0.005})
        async with Stack(config) as stack:
            assert stack.sim.runner.wake_period == 0.005
            await stack.enable()
            home = config.robot.home
            target = Pose(home.position + np.array([0.05, 0.0, 0.05]), home.quaternion)
            await stack.finish(await stack.planner.command("goto", {"pose": target}))
            await asyncio.sleep(0.3)
            error = np.linalg.norm(stack.plant.pose.position - target.position)
            assert error < 1e-3, f"{error * 1e3:.2f} mm from the goto target"

    asyncio.run(asyncio.wait_for(scenario(), 45))
