"""The daemon enables, holds and moves on a robot whose cables are 0.5x or 2x as stiff as
its robot file says, reports the estimate in its state, and still
brakes, naming the drive, on a cable 5 mm off."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cdpr import Pose
from daemon.service.safety import SafetyState, Trigger
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize("factor", [0.5, 2.0])
def test_enable_move_and_a_5_mm_fault_with_a_wrong_stiffness(factor: float) -> None:
    async def scenario() -> None:
        config = config_for("odrive", sim={"plant": {"cable": {"stiffness": 1e5 * factor}}})
        async with Stack(config) as stack:
            service = stack.service
            await stack.enable()
            assert service.state()["stiffness_scale"] == pytest.approx(factor, rel=0.02)
            home = config.robot.home
            target = Pose(home.position + np.array([0.05, 0.0, 0.05]), home.quaternion)
            await stack.finish(await stack.planner.command("goto", {"pose": target}))
            await asyncio.sleep(0.3)
            error = np.linalg.norm(stack.plant.pose.position - target.position)
            assert error < 1e-3, f"{error * 1e3:.2f} mm from the goto target"
            assert service.state()["stiffness_scale"] == pytest.approx(factor, rel=0.02)
            stack.sim.robot.glitch_encoder(3, 0.005)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            fault = service.machine.fault
            assert fault.trigger is Trigger.IMPLAUSIBLE_FEEDBACK, fault
            assert fault.message.startswith("drive 3 (node 3): length"), fault.message

    asyncio.run(asyncio.wait_for(scenario(), 45))
