"""Another node's NMT command or axis state request never leaves a drive in torque
while the daemon says it braked.

Daemon + simulator in one process, a third node on the same loop bus.  While the robot
holds and while it tracks a goto, the third node sends one broadcast: CiA 402 NMT stop,
enter pre-operational, reset communication or reset node (CiA 301 drives process no PDO
outside OPERATIONAL, and a reset communication puts their PDO mapping back to the EDS's:
the daemon's hold RPDO cannot reach them), or for ODrive a Set_Axis_State to every axis.
The daemon brakes, reaches every drive by another route (drivers.cia402.hold_check; the
ODrive's heartbeat and its re-sent state request), confirms each hold from the drive's own
answer, and the simulated platform's TRUE pose moves less than 2 mm over the seconds in
which a drive left in torque at its last command turned the platform by 124 deg.  Bounds
are on the simulated truth, never on wall-clock speed."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from cdpr import Pose
from daemon.service.safety import SafetyState
from drivers.base import Actuation
from drivers.cia402 import codec as cia402
from drivers.cia402.codec import NmtCommand
from drivers.odrive import codec as odrive
from drivers.odrive.codec import AxisState
from sim_bus.bus.loopbus import LoopBus
from tests.daemon.test_daemon_trust import config_for, true_pose
from tests.daemon_stack import Stack

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]
MOVE_ALLOWED = 2e-3  # m the platform's true position may move after the command
TURN_ALLOWED = 5e-3  # rad its true orientation may turn (2 mm at the platform's corners)
WATCH = 5.0  # s of simulated time watched: the free drift shows within 4 s
NMT = {
    "stop": NmtCommand.STOP,
    "pre-operational": NmtCommand.ENTER_PRE_OPERATIONAL,
    "reset-communication": NmtCommand.RESET_COMMUNICATION,
    "reset-node": NmtCommand.RESET_NODE,
}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 100))


def third_node(stack: Stack) -> LoopBus:
    """Another node on the daemon's bus: its frames reach the drives and the daemon."""
    return LoopBus(channel=stack.sim.daemon_bus.channel)


async def fly_or_hold(stack: Stack, tracking: bool) -> None:
    await stack.enable()
    await asyncio.sleep(0.2)
    if tracking:
        home = stack.config.robot.home
        target = Pose(home.position + np.array([0.1, 0.05, 0.0]), home.quaternion)
        reply = await stack.planner.command("goto", {"pose": target})
        assert reply["accepted"], reply
        service = stack.service
        await stack.until(lambda: service.machine.state is SafetyState.TRACKING, 5.0)
        await asyncio.sleep(0.3)  # moving now


async def held_and_still(stack: Stack, start: tuple[np.ndarray, np.ndarray]) -> None:
    """Braked, every hold confirmed by its drive, no simulated drive in torque, and the
    platform's true pose within the bounds of `start` (its pose when the command went
    out, while tracking too: a brake at speed stops it within a few mm, so tracking
    runs compare with the pose once braked) for WATCH seconds of simulated time."""
    service = stack.service
    await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 2.0)
    await stack.until(lambda: all(s.held for s in service.driver.status), 3.0)
    assert service.status()["brake"] == {"confirmed": True, "unconfirmed": []}
    drives = stack.sim.robot.drives
    assert all(d.actuation is not Actuation.TORQUE for d in drives), [d.actuation for d in drives]
    p0, q0 = start
    positions, _ = await stack.watch(WATCH)
    pose = stack.plant.pose
    moved = float(np.max(np.linalg.norm(positions - p0, axis=1)))
    turned = 2.0 * math.acos(min(1.0, abs(float(pose.quaternion @ q0))))
    assert moved < MOVE_ALLOWED, f"the platform moved {moved * 1e3:.2f} mm"
    assert turned < TURN_ALLOWED, f"the platform turned {math.degrees(turned):.3f} deg"
    assert all(d.actuation is not Actuation.TORQUE for d in drives)
    events = [e["event"] for e in stack.events]
    assert "brake_confirmed" in events, events


@pytest.mark.parametrize("tracking", [False, True], ids=["holding", "tracking"])
@pytest.mark.parametrize("command", list(NMT))
def test_an_nmt_broadcast_from_another_node_ends_in_a_confirmed_hold(
    command: str, tracking: bool
) -> None:
    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            await fly_or_hold(stack, tracking)
            intruder = third_node(stack)
            try:
                start = true_pose(stack)
                intruder.send(cia402.encode_nmt(NMT[command], 0))
                if tracking:  # braking at speed: judge the stillness once braked
                    await stack.until(
                        lambda: stack.service.machine.state is SafetyState.BRAKED, 2.0
                    )
                    await asyncio.sleep(0.3)
                    start = true_pose(stack)
                await held_and_still(stack, start)
            finally:
                intruder.shutdown()

    run(scenario())


@pytest.mark.parametrize("tracking", [False, True], ids=["holding", "tracking"])
@pytest.mark.parametrize("state", [AxisState.IDLE, AxisState.CLOSED_LOOP_CONTROL])
def test_an_axis_state_request_from_another_node_ends_in_a_confirmed_hold(
    state: AxisState, tracking: bool
) -> None:
    """ODrive: another node asks every axis for IDLE (the brakes close: the daemon sees a
    drive that no longer follows its forces and brakes) or for closed loop again (the
    firmware restarts the loop: input reset, a gap in torque), then, once braked, puts
    each axis into torque control at its last torque (what a CiA 402 NMT stop leaves):
    the daemon's hold asks for position control again, and every hold is confirmed by
    heartbeat."""

    async def scenario() -> None:
        async with Stack(config_for("odrive")) as stack:
            await fly_or_hold(stack, tracking)
            intruder = third_node(stack)
            service = stack.service
            nodes = stack.config.drives.nodes
            try:
                start = true_pose(stack)
                for node in nodes:
                    intruder.send(odrive.encode_set_axis_state(node, state))
                if state is AxisState.CLOSED_LOOP_CONTROL:  # a restart, not a brake
                    await asyncio.sleep(0.3)
                    service.command("brake", {"reason": "test"})
                await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 2.0)
                await asyncio.sleep(0.3)
                start = true_pose(stack)
                for node in nodes:
                    intruder.send(
                        odrive.encode_set_controller_mode(
                            node, odrive.ControlMode.TORQUE_CONTROL, odrive.InputMode.PASSTHROUGH
                        )
                    )
                await held_and_still(stack, start)
            finally:
                intruder.shutdown()

    run(scenario())
