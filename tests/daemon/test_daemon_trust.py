"""The brake holds trusted lengths, never a forged or glitching one.

Daemon + simulator in one process, both drivers: a forged feedback frame for cable 0
(4.1 m; really ~2.33 m), delivered right after the drive's real position frame (402: its
TPDO1, an ODrive: each real estimate), and a glitching encoder, each while HOLDing and while
IDLE.  The daemon brakes naming the drive, and the simulated platform's TRUE pose (the
plant, not what the daemon measures) stays within 2 mm of where it was.  A forged
boot-up heartbeat is a drive fault.  Bounds are on the simulated truth and in cycles,
never on wall-clock speed."""

from __future__ import annotations

import asyncio
import math
import re

import can
import numpy as np
import pytest

from daemon.config import DaemonConfig, load_config
from daemon.service.safety import SafetyState, Trigger
from drivers.cia402 import codec as cia402
from drivers.cia402.codec import NmtState
from drivers.odrive import codec as odrive
from drivers.odrive.codec import Cmd
from tests.daemon_stack import DRIVER_CONFIGS, Stack
from tests.processes import patient_watchdogs

pytestmark = pytest.mark.timeout(60)
PROTOCOLS = ["cia402", "odrive"]
FORGED = 4.1  # m, the length the attacker claims for cable 0
MOVE_ALLOWED = 2e-3  # m the platform's true position may move
TURN_ALLOWED = 5e-3  # rad its true orientation may turn (2 mm at the platform's corners)


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 45))


def config_for(protocol: str) -> DaemonConfig:
    """The example config with patient drive watchdogs: on a busy host a stalled loop
    would otherwise end a run by a watchdog fault before the trust checks are seen."""
    return load_config(DRIVER_CONFIGS[protocol], patient_watchdogs)


class Forger:
    """Inserts a forged copy of cable 0's position frame right after every real one the
    simulated drive sends (402: a TPDO1 with the position of `length`, before the drive's
    TPDO2 completes the sample; ODrive: an encoder estimate), so the daemon reads the
    forgery last.  `answer` (402): a whole forged answer (TPDO1 + TPDO2) after the
    drive's, which the host drops as a second answer to the SYNC."""

    def __init__(self, stack: Stack, length: float, answer: bool = False) -> None:
        config = stack.config
        self.answer = answer
        self.protocol = config.drives.protocol
        self.node = config.drives.nodes[0]
        self.position = config.drives.scalings_for(config.robot)[0].position(length)
        self.sent = 0
        robot = stack.sim.robot
        handle, advance = robot.handle, robot.advance_to
        robot.handle = lambda message, t: self._forge(handle(message, t))
        robot.advance_to = lambda t: self._forge(advance(t))

    def _forge(self, frames: list[can.Message]) -> list[can.Message]:
        out = []
        for frame in frames:
            out.append(frame)
            if self.protocol == "cia402" and frame.arbitration_id == cia402.TPDO1_BASE + self.node:
                statusword, _, mode = cia402.decode_tpdo1(frame.arbitration_id, frame.data)
                self.forged = cia402.encode_tpdo1(self.node, statusword, round(self.position), mode)
                if not self.answer:
                    out.append(self.forged)
                    self.sent += 1
            elif self.answer and frame.arbitration_id == cia402.TPDO2_BASE + self.node:
                out += [self.forged, cia402.encode_tpdo2(self.node, 0)]
                self.sent += 1
            elif self.protocol == "odrive" and frame.arbitration_id == (
                self.node << 5 | Cmd.GET_ENCODER_ESTIMATES
            ):
                out.append(odrive.encode_encoder_estimates(self.node, self.position, 0.0))
                self.sent += 1
        return out


def true_pose(stack: Stack) -> tuple[np.ndarray, np.ndarray]:
    pose = stack.plant.pose
    return pose.position.copy(), pose.quaternion.copy()


async def assert_stays(stack: Stack, start: tuple[np.ndarray, np.ndarray], seconds: float) -> None:
    """The platform's true pose stays within MOVE_ALLOWED / TURN_ALLOWED of `start` for
    `seconds` (sampled every 5 ms)."""
    p0, q0 = start
    moved = turned = 0.0
    for _ in range(round(seconds / 0.005)):
        p, q = true_pose(stack)
        moved = max(moved, float(np.linalg.norm(p - p0)))
        turned = max(turned, 2.0 * math.acos(min(1.0, abs(float(q @ q0)))))
        await asyncio.sleep(0.005)
    assert moved < MOVE_ALLOWED, f"the platform moved {moved * 1e3:.2f} mm"
    assert turned < TURN_ALLOWED, f"the platform turned {math.degrees(turned):.3f} deg"


def assert_braked_naming_drive_0(stack: Stack) -> None:
    fault = stack.service.machine.fault
    assert fault is not None and fault.trigger is Trigger.IMPLAUSIBLE_FEEDBACK, fault
    node = stack.config.drives.nodes[0]
    assert fault.message.startswith(f"drive 0 (node {node}): length "), fault.message
    brakes = [e for e in stack.events if e["event"] == "brake"]
    assert brakes[0]["trigger"] == "implausible_feedback"
    assert brakes[0]["message"] == fault.message


async def trusted_again(stack: Stack) -> None:
    """The feedback is true again: the condition clears (reset may go ahead) and the
    hold target follows the measurements again."""
    service = stack.service

    def cleared() -> bool:
        return all(f.trigger is not Trigger.IMPLAUSIBLE_FEEDBACK for f in service.faults)

    await stack.until(cleared, 1.0)
    await asyncio.sleep(0.05)
    measured = [fb.length for fb in service.driver.feedback]
    assert service.trust.held == pytest.approx(measured, abs=1e-4)


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("enabled", [True, False], ids=["hold", "idle"])
def test_a_forged_length_brakes_naming_the_drive_and_nothing_moves(
    protocol: str, enabled: bool
) -> None:
    async def scenario() -> None:
        async with Stack(config_for(protocol)) as stack:
            service = stack.service
            if enabled:
                await stack.enable()
            await asyncio.sleep(0.2)
            start = true_pose(stack)
            forger = Forger(stack, FORGED)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            await assert_stays(stack, start, 0.5)  # the forgery goes on meanwhile
            assert forger.sent > 100
            assert_braked_naming_drive_0(stack)
            assert f"length {FORGED:.4f} m" in service.machine.fault.message
            assert "max_cable_speed" in service.machine.fault.message
            assert any("drive 0" in c for c in service.status()["conditions"])

    run(scenario())


@pytest.mark.parametrize("enabled", [True, False], ids=["hold", "idle"])
def test_a_forged_second_answer_to_one_sync_brakes_naming_the_drive(enabled: bool) -> None:
    """The forger's whole answer (TPDO1 + TPDO2) comes after the drive's, every SYNC:
    the host drops it, but the two answers to one SYNC are 1.8 m apart."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            service = stack.service
            if enabled:
                await stack.enable()
            await asyncio.sleep(0.2)
            start = true_pose(stack)
            forger = Forger(stack, FORGED, answer=True)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            await assert_stays(stack, start, 0.5)  # the forgery goes on meanwhile
            assert forger.sent > 100
            assert_braked_naming_drive_0(stack)
            message = service.machine.fault.message
            named = re.match(f"drive 0 .*: length {FORGED:.4f} m and ([0-9.]+) m in two", message)
            assert named, message
            assert float(named[1]) == pytest.approx(service.trust.held[0], abs=1e-3)  # the true
            assert "answers to one SYNC" in message and "max_cable_speed" in message
            rejected = service.driver.counters.rejected["TPDO after the sample was complete"]
            assert rejected > 100  # the host dropped them: the drive's answers stood

    run(scenario())


@pytest.mark.parametrize("protocol", PROTOCOLS)
@pytest.mark.parametrize("enabled", [True, False], ids=["hold", "idle"])
@pytest.mark.parametrize("offset", [0.1, -0.004], ids=["jump", "small"])
def test_a_glitching_encoder_brakes_naming_the_drive_and_nothing_moves(
    protocol: str, enabled: bool, offset: float
) -> None:
    """A jump beyond the step bound, and one of 4 mm that only the drive's own rate
    (zero: it stands still) gives away."""

    async def scenario() -> None:
        async with Stack(config_for(protocol)) as stack:
            service = stack.service
            if enabled:
                await stack.enable()
            await asyncio.sleep(0.2)
            start = true_pose(stack)
            stack.sim.robot.glitch_encoder(0, offset)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            await assert_stays(stack, start, 0.5)
            assert_braked_naming_drive_0(stack)
            stack.sim.robot.glitch_encoder(0, 0.0)
            await trusted_again(stack)

    run(scenario())


@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_reset_judges_the_feedback_afresh(protocol: str) -> None:
    """A cable that stays off is a condition reset will not clear while it cannot fit
    one pose with the others (a forged 4.1 m); one that does fit (1.5 mm, within the
    robot's FK residual bound: indistinguishable from calibration) is trusted afresh by
    reset, as a restart would."""

    async def scenario() -> None:
        async with Stack(config_for(protocol)) as stack:
            service = stack.service
            await asyncio.sleep(0.2)
            stack.sim.robot.glitch_encoder(0, FORGED - service.trust.held[0])
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            with pytest.raises(Exception, match=r"faults persist: drive 0 \(node \d+\)"):
                await service.command("reset", {})
            # true again, then 1.5 mm off from one cycle to the next: the per-cable checks
            # name it (across a long gap, noisy rates integrate to about as much: there
            # only the FK fit at reset and the consistency check remain)
            stack.sim.robot.glitch_encoder(0, 0.0)
            await trusted_again(stack)
            stack.sim.robot.glitch_encoder(0, 1.5e-3)
            await stack.until(lambda: any("drive 0" in f.message for f in service.faults), 1.0)
            await service.command("reset", {})
            assert service.machine.state is SafetyState.IDLE
            assert service.faults == []

    run(scenario())


def test_a_forged_boot_up_heartbeat_is_a_drive_fault() -> None:
    """A CiA 402 drive that rebooted lost its configuration and position: a boot-up
    heartbeat (here forged: the drive stays operational) brakes naming it, and reset is
    refused until the daemon starts it again.  ODrive 0.6 sends no boot-up message."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            service = stack.service
            await stack.enable()
            await asyncio.sleep(0.1)
            start = true_pose(stack)
            stack.sim.runner._send([cia402.encode_heartbeat(4, NmtState.BOOT_UP)])
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 1.0)
            fault = service.machine.fault
            assert fault.trigger is Trigger.DRIVE_FAULT
            assert fault.message.startswith("drive 3 reports fault 0x0000: node 4: the drive ")
            await assert_stays(stack, start, 0.3)
            with pytest.raises(Exception, match="node 4 is not started"):
                await service.command("reset", {})

    run(scenario())
