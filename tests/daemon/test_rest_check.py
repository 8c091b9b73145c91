"""The stored zero and a named pose checked against what the robot shows at rest (the
tensions the drives measure, the FK residual), daemon + simulator in one process: a
believed pose 300 mm or 50 mm above the true one refuses enable and nothing moves; `home`
at a pose the platform is not resting at is refused and changes nothing.  Bounds are on
the simulated truth."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cdpr.controller import ParallelController, static_tensions
from cdpr.pose import Pose
from daemon.config import DaemonConfig
from daemon.service.api import CommandError
from daemon.service.calibration_state import load_state, robot_identity, save_state, state_path
from daemon.service.rest_check import judge
from daemon.service.safety import SafetyState
from tests.daemon.test_homing import homing_config, run, settle
from tests.daemon_stack import Stack

pytestmark = pytest.mark.timeout(120)
STILL = 2e-3  # m: the true platform moves less than this (the hold's own settling)
ENABLE_REFUSED = r"cannot enable: the stored length offsets put the platform at .* but the tensions"
HOME_REFUSED = r"home: the platform is not resting at pose 'high': the tensions the drives measure"


def raised(pose: Pose, dz: float) -> Pose:
    return Pose(np.add(pose.position, (0.0, 0.0, dz)), pose.quaternion)


async def homed(stack: Stack) -> None:
    """Homed at the true pose (named "dock"), then disabled: offsets stored, robot idle."""
    await settle(stack)
    stack.service.robot.poses["dock"] = stack.plant.pose
    await stack.planner.command("home", {"pose_name": "dock"})


@pytest.mark.parametrize("dz", [0.3, 0.05])
def test_offsets_that_put_the_platform_higher_refuse_enable_and_nothing_moves(
    dz: float, tmp_path: Path
) -> None:
    """The state file's offsets edited so that the lengths fit the true pose + dz in z
    (each offset moved by the model's length change): start-up trusts them (they fit a
    pose), but the tensions at rest do not hold the platform there."""
    config = homing_config("cia402", tmp_path, None)

    async def first() -> None:
        async with Stack(config) as stack:
            await homed(stack)

    async def edited() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await settle(stack)
            assert service.machine.state is SafetyState.IDLE
            before = stack.plant.pose.position.copy()
            with pytest.raises(CommandError, match=ENABLE_REFUSED) as refused:
                await service.command("enable", {})
            believed = float(re.search(r"platform at \(.*, (\S+)\) m", str(refused.value))[1])
            assert abs(believed - (before[2] + dz)) < 5e-3, (believed, before)
            positions, _ = await stack.watch(1.0)
            assert service.machine.state is SafetyState.IDLE
            moved = np.abs(positions - before).max()
            assert moved < STILL, moved

    run(first())
    robot = config.robot
    shift = robot.cable_lengths(raised(robot.home, dz)) - robot.cable_lengths(robot.home)
    edit_offsets(config, shift)
    run(edited())


def edit_offsets(config: DaemonConfig, shift: np.ndarray) -> None:
    """The stored offsets moved by `shift` (m) and the file signed again: a state file
    whose checksum and identity hold but whose zero is wrong (restored from before a
    cable was re-spooled, say)."""
    robot = config.robot
    path = state_path(config.state_dir, robot.name)
    identity = robot_identity(robot, config.drives)
    state = load_state(path, robot.name, robot.n_cables, identity)
    save_state(path, replace(state, offsets=tuple(np.add(state.offsets, shift))))


def test_home_at_a_pose_the_platform_is_not_resting_at_is_refused(tmp_path: Path) -> None:
    """The platform rests at home; `home` is told it rests at a pose 0.3 m higher (the
    finding: the platform 0.3 m above the home pose, homed at home).  Refused naming the
    check and the figures; the offsets in force and on disk are unchanged, enable still
    works, and nothing moved."""
    config = homing_config("cia402", tmp_path, None)

    async def scenario() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await homed(stack)
            stored = state_path(tmp_path, "reference8").read_text()
            before, at = service.offsets.offsets, stack.plant.pose.position.copy()
            service.robot.poses["high"] = raised(stack.plant.pose, 0.3)
            with pytest.raises(CommandError, match=HOME_REFUSED) as refused:
                await stack.planner.command("home", {"pose_name": "high"})
            assert "net force [" in str(refused.value) and "safety.rest_force" in str(refused.value)
            assert service.offsets.offsets == before
            assert state_path(tmp_path, "reference8").read_text() == stored
            assert service.machine.state is SafetyState.IDLE
            assert np.abs(stack.plant.pose.position - at).max() < STILL
            await stack.enable()

    run(scenario())


def test_the_residual_is_the_statics_of_the_pose() -> None:
    """Pure: the model's own tensions at rest at home leave nothing at home and the
    vertical figures of the finding 50 mm and 300 mm higher (internal forces ~300 N)."""
    config = homing_config("cia402", Path("/nonexistent"), None)
    robot = config.robot
    solver = ParallelController(robot, config.controller, config.drives.force_lag).tension
    forces = -static_tensions(robot, solver, robot.home)
    residual, refusal = judge(robot, robot.home, forces, 15.0, 5.0)
    assert refusal is None and np.abs(residual.force).max() < 1e-9
    for dz, vertical in [(0.05, 44.3), (0.3, 267.0)]:
        residual, refusal = judge(robot, raised(robot.home, dz), forces, 15.0, 5.0)
        assert residual.force[2] == pytest.approx(vertical, abs=0.1)
        assert refusal is not None and f"net force [0.0, 0.0, {vertical:.1f}] N" in refusal
