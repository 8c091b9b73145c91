"""The payload through the daemon: identify_payload against a simulated
robot carrying a payload its robot file does not know, the payload command, the
payload_limit brake and the config's errors."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from cdpr import ConfigError
from daemon.config import DaemonConfig
from daemon.interface.messages import decode_command
from daemon.service.api import CommandError
from daemon.service.safety import SafetyState, Trigger
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(90)

# 2 kg hung 3.4 cm aside and 10 cm below the reference point of reference8's 10 kg
# platform (centre of mass (0, 0, -0.02)): 12 kg, centre of mass (0.005, -0.0025, -0.0333)
# (a torque the file's model, frozen, holds within the orientation bound while it tilts)
PAYLOAD = {"mass": 2.0, "position": [0.03, -0.015, -0.10]}
TRUE_MASS = 12.0
TRUE_COM = np.array([0.005, -0.0025, -0.4 / 12.0])


def _config(adaptation: dict) -> DaemonConfig:
    return config_for(
        "cia402",
        sim={"plant": {"step": 0.001, "mismatch": {"payload": PAYLOAD}}},
        controller={"adaptation": adaptation},
    )


@pytest.mark.slow  # over 10 s of the default run's 10 minutes
def test_identify_payload_estimates_and_applies_the_payload() -> None:
    """With the online estimate frozen (the file's model), identify_payload holds five
    poses and finds the payload from the forces: within 1 % and 3 mm, the tilted poses
    revealing the vertical part too; applied, the controller's model and the state show
    it."""

    async def scenario() -> None:
        async with Stack(_config({"frozen": True})) as stack:
            await stack.enable()
            result = await stack.planner.command("identify_payload", {"apply": True})
            assert result["poses"] == 5 and result["applied"] is True
            assert result["mass"] == pytest.approx(TRUE_MASS, rel=0.01), result
            assert np.abs(np.subtract(result["center_of_mass"], TRUE_COM)).max() < 3e-3, result
            assert result["mass_std"] < 0.1 and max(result["center_of_mass_std"]) < 3e-3, result
            state = stack.service.state()["payload"]
            assert state["mass"] == pytest.approx(result["mass"]) and state["frozen"] is True
            assert stack.service.controller.robot.platform.mass == pytest.approx(result["mass"])
            assert stack.service.machine.state is SafetyState.HOLD
            assert stack.service.machine.fault is None

    asyncio.run(asyncio.wait_for(scenario(), 80))


def test_the_payload_command_freezes_and_refuses_a_mass_beyond_the_limits() -> None:
    async def scenario() -> None:
        async with Stack(_config({})) as stack:
            await stack.enable()
            reply = await stack.planner.command("payload", {"frozen": True})
            assert reply["frozen"] is True and stack.service.controller.payload.frozen
            with pytest.raises(CommandError, match=r"adaptation\.mass_max 15 kg"):
                await stack.planner.command(
                    "payload", {"mass": 20.0, "center_of_mass": (0.0, 0.0, 0.0)}
                )

    asyncio.run(asyncio.wait_for(scenario(), 30))


def test_a_payload_beyond_the_limits_brakes_naming_the_trigger() -> None:
    """mass_max 11 kg and 12 kg on the platform: the estimate crosses the limit while the
    robot holds, the daemon brakes with payload_limit (not a tracking error)."""

    async def scenario() -> None:
        async with Stack(_config({"mass_max": 11.0})) as stack:
            service = stack.service
            await stack.enable()
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 10.0)
            fault = service.machine.fault
            assert fault.trigger is Trigger.PAYLOAD_LIMIT, fault
            assert "adaptation.mass_max 11 kg" in fault.message, fault.message

    asyncio.run(asyncio.wait_for(scenario(), 30))


def test_adaptation_limits_below_the_robot_file_are_a_named_config_error() -> None:
    with pytest.raises(ConfigError, match=r"controller\.adaptation\.mass_max: the robot file's"):
        _config({"mass_max": 9.0})


@pytest.mark.parametrize(
    ("name", "body", "field", "message"),
    [
        ("payload", {"mass": 11.0}, "center_of_mass", "center_of_mass missing"),
        ("payload", {"mass": -1.0, "center_of_mass": [0, 0, 0]}, "mass", "positive number"),
        ("payload", {"frozen": 1}, "frozen", "payload.frozen: expected true or false"),
        ("identify_payload", {"apply": "yes"}, "apply", "expected true or false"),
    ],
)
def test_payload_commands_name_a_bad_argument(
    name: str, body: dict, field: str, message: str
) -> None:
    with pytest.raises(CommandError, match=message) as raised:
        decode_command(name, body)
    assert raised.value.code == "bad_request" and raised.value.details["field"] == field
    with pytest.raises(CommandError, match="'pose'"):
        decode_command(name, {"pose": 1})
