"""Pretension through the daemon, daemon + simulator in one process:
the platform rests on the simulator's docking fixture (sim.plant.fixture) with slack
cables; `pretension` winds them in, tensions them and closes the position loop in the
core's cycle.  Bounds are on the simulated truth; nothing is timed."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.config import DaemonConfig, load_config
from daemon.interface.messages import decode_command
from daemon.service.api import COMMANDS, CommandError
from daemon.service.calibration_state import state_path
from daemon.service.safety import SafetyState, Trigger
from tests.daemon.test_calibrate_cli import config_file
from tests.daemon_stack import DRIVER_CONFIGS, Stack
from tests.loopback import free_port
from tests.processes import cdprd, connect, finish, patient_watchdogs, start_daemon, wait_status

pytestmark = pytest.mark.timeout(120)
SLACK = [0.0, 0.06, 0.02, 0.05, 0.01, 0.03, 0.04, 0.06]


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 90))


def slack_config(
    protocol: str,
    pretension: dict | None = None,
    mismatch: dict | None = None,
    state_dir: Path | None = None,
) -> DaemonConfig:
    def edit(data: dict) -> None:
        patient_watchdogs(data)
        if state_dir is not None:
            data["state_dir"] = str(state_dir)
        plant = data.setdefault("sim", {}).setdefault("plant", {})
        plant["fixture"] = {"slack_m": SLACK}
        plant["mismatch"] = mismatch or {}
        data["pretension"] = pretension or {}

    return load_config(DRIVER_CONFIGS[protocol], edit)


class Truth:
    """Watches the simulated truth while a command runs: the platform's largest
    displacement from where it rested and the largest cable tension."""

    def __init__(self, stack: Stack) -> None:
        self.plant = stack.plant
        self.rest = self.plant.pose.position.copy()
        self.moved = 0.0
        self.peak = 0.0

    async def run(self) -> None:
        while True:
            self.sample()
            await asyncio.sleep(0.002)

    def sample(self) -> None:
        moved = float(np.linalg.norm(self.plant.pose.position - self.rest))
        self.moved = max(self.moved, moved)
        self.peak = max(self.peak, float(self.plant.tensions.max()))


async def started(stack: Stack) -> None:
    """Until the start-up trust check has judged the first set: slack cables fit no pose."""
    service = stack.service
    await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 5.0)
    assert service.machine.fault.trigger is Trigger.IMPLAUSIBLE_FEEDBACK
    assert "fit no pose" in service.machine.fault.message


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
@pytest.mark.parametrize("protocol", ["cia402", "odrive"])
def test_pretension_from_slack_cables_holds_the_platform_where_it_rested(protocol: str) -> None:
    config = slack_config(protocol)
    force_max = float(config.robot.force_max.min())

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            with pytest.raises(CommandError, match="cannot enable while braked"):
                await stack.planner.command("enable", {})
            truth = Truth(stack)
            watcher = asyncio.create_task(truth.run())
            reply = await stack.planner.command("pretension", {})
            assert reply["state"] == "hold"
            summary = reply["pretension"]
            assert summary["fault"] is None
            taut = summary["taut_s"]
            assert all(t is not None for t in taut)
            assert max(taut) > taut[0]  # the slackest cables are taut last
            assert reply["method"] == "pretension at pose home"
            assert reply["loop_close_step_n"] < 3.0  # N, of ~270 N
            # the fixture's share handed over, then holding: count cycles, not seconds
            before = service.stats.cycles
            await stack.until(lambda: service.pretension.phase == "closed", 30.0)
            await stack.until(lambda: service.stats.cycles > before + 1000, 30.0)
            watcher.cancel()
            truth.sample()
            assert service.machine.state is SafetyState.HOLD
            assert truth.moved < 2e-3
            assert truth.peak < 0.7 * force_max
            assert service.status()["pretension"]["phase"] == "closed"
            # once holding, pretension is refused like enable
            with pytest.raises(CommandError, match="cannot pretension while hold"):
                await stack.planner.command("pretension", {})

    run(main())


def test_a_pretension_whose_caller_went_away_still_closes_the_loop() -> None:
    """The command's caller is cancelled while the cables wind in (a client that gave
    up): the daemon still homes, closes the loop and holds, not left in PRETENSION."""
    config = slack_config("cia402")

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            command = asyncio.create_task(stack.planner.command("pretension", {}))
            await stack.until(lambda: service.machine.state is SafetyState.PRETENSION, 10.0)
            command.cancel()
            with pytest.raises(asyncio.CancelledError):
                await command
            await stack.until(lambda: service.machine.state is SafetyState.HOLD, 30.0)
            assert service.offsets.method == "pretension at pose home"

    run(main())


def test_an_abort_after_homing_stores_the_offsets_it_left_in_force(tmp_path: Path) -> None:
    """Braked after the pretension homed, before the loop closed: the offsets it homed
    (at rest on the fixture) stay in force, and the state directory holds them, so that
    the next start-up reads what was in force; the refusal says so."""
    config = slack_config("cia402", state_dir=tmp_path)
    path = state_path(tmp_path, config.robot.name)

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            loop = asyncio.get_running_loop()

            def on_event(event: dict) -> None:
                if event.get("event") == "homed":  # in the cycle: brake right after it
                    loop.call_soon(service.command, "brake", {"reason": "stop after homing"})

            service.subscribe(on_event)
            with pytest.raises(CommandError, match="pretension aborted: BRAKE") as refused:
                await stack.planner.command("pretension", {})
            assert service.machine.state is SafetyState.BRAKED
            assert service.status()["pretension"]["phase"] == "aborted"
            assert service.offsets.method == "pretension at pose home"
            in_force = service.offsets.offsets
            assert refused.value.details["offsets"] == in_force
            assert refused.value.details["stored"] == str(path)
            stored = json.loads(path.read_text())
            assert stored["offsets"] == in_force
            assert stored["method"] == "pretension at pose home"

    run(main())


def test_a_cable_that_never_gets_taut_brakes_naming_it() -> None:
    """Cable 3 snapped: winding it in finds no tension; after max_wind_in it brakes."""
    config = slack_config("cia402", {"max_wind_in": 0.12})

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            stack.sim.robot.snap_cable(3)
            with pytest.raises(CommandError, match=r"cable 3 wound in 0\.12\d m without") as err:
                await stack.planner.command("pretension", {})
            assert "pretension aborted: BRAKE [pretension]" in str(err.value)
            assert service.machine.state is SafetyState.BRAKED
            assert service.machine.fault.trigger is Trigger.PRETENSION
            assert service.status()["pretension"]["phase"] == "aborted"

    run(main())


def test_a_platform_that_moves_during_the_ramp_brakes_naming_the_motion() -> None:
    """Ramping open loop to the whole weight (carry 1) of a platform 20 % lighter than
    the robot file lifts it off the fixture: braked at max_motion, held there."""
    config = slack_config("cia402", {"carry": 1.0}, {"mass_scale": 0.8})

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            truth = Truth(stack)
            watcher = asyncio.create_task(truth.run())
            with pytest.raises(CommandError, match=r"the platform moved \d+\.\d\d mm \(max_motion"):
                await stack.planner.command("pretension", {})
            assert service.machine.fault.trigger is Trigger.PRETENSION
            assert "during the tension ramp" in service.machine.fault.message
            before = service.stats.cycles
            await stack.until(lambda: service.stats.cycles > before + 250, 30.0)
            watcher.cancel()
            truth.sample()
            assert truth.moved < 5e-3  # the brake holds it near where it was stopped

    run(main())


def test_pretension_is_refused_for_an_unknown_pose_and_changes_nothing() -> None:
    config = slack_config("odrive")

    async def main() -> None:
        async with Stack(config) as stack:
            await started(stack)
            with pytest.raises(CommandError, match=r"pretension: no pose 'dock' .*poses: home"):
                await stack.planner.command("pretension", {"pose_name": "dock"})
            assert stack.service.machine.state is SafetyState.BRAKED
            assert stack.service.pretension is None

    run(main())


def test_pretension_takes_a_pose_name_over_zenoh() -> None:
    assert "pretension" in COMMANDS
    assert decode_command("pretension", {"pose": "dock"}) == {"pose_name": "dock"}
    assert decode_command("pretension", {}) == {}
    with pytest.raises(CommandError, match=r"pretension\.pose: expected a pose name"):
        decode_command("pretension", {"pose": 3})


@pytest.mark.slow  # the daemon as a process
@pytest.mark.timeout(240)
def test_cdprd_pretension_through_the_cli_against_a_daemon_process(tmp_path: Path) -> None:
    """`cdprd run --sim` with slack cables on the fixture starts braked (the lengths fit
    no pose); `cdprd pretension` brings it to HOLD and its homing's offsets are stored."""
    port = free_port()
    path = config_file(tmp_path, port)
    data = yaml.safe_load(path.read_text())
    data.setdefault("sim", {}).setdefault("plant", {})["fixture"] = {"slack_m": SLACK}
    path.write_text(yaml.safe_dump(data))
    daemon = start_daemon(path, "--sim")
    try:
        with connect(port, daemon) as client:  # closed on a failure too
            wait_status(client, "braked", 30.0)
            done = cdprd("pretension", "--connect", f"tcp/127.0.0.1:{port}", "--json")
            assert done.returncode == 0, done.stderr
            result = json.loads(done.stdout)
            assert result["state"] == "hold" and result["pretension"]["fault"] is None
            assert result["loop_close_step_n"] < 3.0
            stored = json.loads(state_path(tmp_path / "state", "reference8").read_text())
            assert stored["offsets"] == result["offsets"]
            assert stored["method"] == "pretension at pose home"
            assert client.status()["state"] == "hold"
    finally:
        finish(daemon)


def test_pretension_of_a_hanging_platform_brakes_before_it_drops() -> None:
    """No fixture: the platform hangs on taut cables (IDLE, held).  Winding in at 15 N
    lets the cables pay out under the weight: braked at once, naming the cable."""
    config = load_config(DRIVER_CONFIGS["cia402"], patient_watchdogs)

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await stack.until(lambda: all(np.isfinite(service.trust.held)), 5.0)
            assert service.machine.state is SafetyState.IDLE
            truth = Truth(stack)
            watcher = asyncio.create_task(truth.run())
            resting = r"cable \d pays out at .*\(is the platform resting"
            with pytest.raises(CommandError, match=resting):
                await stack.planner.command("pretension", {})
            before = service.stats.cycles
            await stack.until(lambda: service.stats.cycles > before + 250, 30.0)
            watcher.cancel()
            truth.sample()
            assert truth.moved < 5e-3  # ~2.2 mm: a cycle or two of falling, then the brake

    run(main())


def test_feedback_lost_during_pretension_brakes_naming_the_drive() -> None:
    config = slack_config("odrive")

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            command = asyncio.ensure_future(stack.planner.command("pretension", {}))
            await stack.until(lambda: service.machine.state is SafetyState.PRETENSION, 10.0)
            stack.sim.robot.silence(5)
            with pytest.raises(CommandError, match=r"pretension aborted: BRAKE \[stale_feedback\]"):
                await command
            assert "drive 5: no feedback" in service.machine.fault.message
            assert service.status()["pretension"]["phase"] == "aborted"

    run(main())


def test_a_brake_while_the_drives_enable_for_pretension_aborts_it() -> None:
    """Braked (slack cables at start-up), then braked again while the drives enable:
    the state was and is BRAKED, and the pretension must not start all the same."""
    config = slack_config("cia402")

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            enable = service.driver.enable

            async def enable_then_brake(*args: object) -> None:
                await enable(*args)
                service.command("brake", {"reason": "operator stop"})

            service.driver.enable = enable_then_brake
            with pytest.raises(CommandError, match="pretension aborted"):
                await stack.planner.command("pretension", {})
            assert service.machine.state is SafetyState.BRAKED
            assert service.pretension is None

    run(main())


def test_a_disable_while_the_fixture_s_share_is_handed_over_ends_the_pretension() -> None:
    """Disabled in HOLD right after the loop closed, before unload_time has handed the
    fixture's share to the controller: the robot is IDLE, the pretension aborted naming
    the disable, and no later cycle goes on unloading it (the cycle's procedure, ended)."""
    config = slack_config("cia402", pretension={"unload_time": 5.0})

    async def main() -> None:
        async with Stack(config) as stack:
            service = stack.service
            await started(stack)
            reply = await stack.planner.command("pretension", {})
            assert reply["state"] == "hold"
            assert service.pretension.phase == "unload"
            await stack.planner.command("disable", {})
            assert service.machine.state is SafetyState.IDLE
            before = service.stats.cycles
            await stack.until(lambda: service.stats.cycles > before + 50, 10.0)
            summary = service.status()["pretension"]
            assert (summary["phase"], summary["fault"]) == ("aborted", "disabled")

    run(main())
