"""The platform's body and the environment in the daemon (DESIGN §18, cdpr.body): the
config's `environment:` section refused where it cannot hold, a goto that keeps the
reference point inside the box but takes the platform's corners through the floor
refused naming the corner, a box on a cable's way refused naming the cable, and the
runtime monitor braking on a body below the floor and on one in a box.  In-process
daemon + simulator; bounded waits only."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import numpy as np
import pytest
import yaml

from cdpr import ConfigError, Pose
from daemon.config import load_config, parse_config
from daemon.service.api import CommandError
from daemon.service.safety import SafetyMonitor, SafetyState, Trigger
from tests.daemon.test_daemon_validation import _home, _refused
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(60)
CONFIG = Path(__file__).resolve().parents[2] / "config"
# a bench under the platform, narrower than it (no corner of the platform over it) and
# clear of the cables: at home the platform's bottom face is 0.1 m above it
BENCH = {"boxes": [{"name": "bench", "min": [-0.15, -0.15, 0.5], "max": [0.15, 0.15, 0.85]}]}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 45))


def _data(**sections) -> dict:
    data = yaml.safe_load((CONFIG / "reference8-cia402.yaml").read_text())
    data.update(sections)
    return data


@pytest.mark.parametrize(
    ("environment", "message"),
    [
        (
            {"planes": [{"point": [0, 0, 0.5], "normal": [0, 0, 1]}]},
            r"^test.yaml: environment.planes.0: cable 1's anchor \[1.5, 1.5, 0.0\] lies 0.5 m "
            r"behind plane 'plane 0': its cable would cross it$",
        ),
        (
            {"planes": [{"point": [0, 0, 0], "normal": [0, 0, 0]}]},
            r"^test.yaml: environment.planes.0.normal: normal must be a non-zero vector",
        ),
        (
            {"boxes": [{"name": "crate", "min": [1, 1, 0], "max": [1, 2, 1]}]},
            r"^test.yaml: environment.boxes.0: min \[1.0, 1.0, 0.0\] must lie below max",
        ),
        (
            {"boxes": [{"name": "winch", "min": [1.4, 1.4, -0.1], "max": [1.6, 1.6, 0.1]}]},
            r"environment.boxes.0: cable 1's anchor \[1.5, 1.5, 0.0\] lies inside box 'winch'",
        ),
        (
            {"boxes": [{"name": "post", "min": [-0.02, -0.02, 0.0], "max": [0.02, 0.02, 1.0]}]},
            r"^test.yaml: environment: at the home pose the platform body crosses box 'post'",
        ),
        ({"walls": []}, r"environment.walls: Extra inputs are not permitted"),
    ],
)
def test_an_environment_that_cannot_hold_is_refused_naming_the_key(
    environment: dict, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config(_data(environment=environment), CONFIG, "test.yaml")


def test_the_shipped_configs_load_with_an_environment() -> None:
    """A floor at z = 0 (the lower anchors stand on it) and a table away from the cables."""
    environment = {
        "planes": [{"name": "floor", "point": [0, 0, 0], "normal": [0, 0, 1]}],
        "boxes": [{"name": "table", "min": [-0.4, -0.4, 0.0], "max": [0.4, 0.4, 0.6]}],
    }
    config = parse_config(_data(environment=environment), CONFIG, "test.yaml")
    assert [p.name for p in config.pose_limits.environment.planes] == ["floor"]
    assert config.reference_limits.violation(config.robot.home) is None
    # the platform set down on the table: its lower corners in it
    low = config.reference_limits.violation(Pose((0.0, 0.0, 0.8)))
    assert low is not None and low.limit == "environment" and "box 'table'" in low.detail


def test_the_runtime_check_brakes_on_a_corner_below_the_floor() -> None:
    """The measured pose at z = 0.10 m: the reference point is inside the box, the lower
    corners 0.2 m below the floor: POSE_LIMIT, naming the corner."""
    config = load_config(CONFIG / "reference8-cia402.yaml")
    monitor = SafetyMonitor(config)
    from tests.daemon.test_safety import _output_at

    base = _output_at(config, config.robot.home)
    low = Pose((0.0, 0.0, 0.10))
    fault = monitor.check_output(base._replace(pose=low, theta_d=np.zeros(6)))
    assert fault is not None and fault.trigger is Trigger.POSE_LIMIT
    assert fault.message.startswith("platform corner 1 (0.2, -0.2, -0.3 m in the platform frame)")
    assert "at z = -0.2000 m outside [0.0000, 2.5000] m" in fault.message


def test_a_goto_that_takes_the_corners_through_the_floor_is_refused_naming_the_corner() -> None:
    """The case found: a goto to z = 0.10 m, whose reference point is inside the box
    (z >= 0 less 20 mm), would put the platform's lower corners at z = -0.2 m."""

    async def scenario() -> None:
        async with Stack(config_for("cia402")) as stack:
            await stack.enable()
            target = Pose((0.0, 0.0, 0.10))
            err = await _refused(stack, stack.planner.command("goto", {"pose": target}))
            assert err.details["limit"] == "workspace_min" and "waypoint" not in err.details
            assert err.reason.startswith(
                "goto rejected: workspace_min: platform corner 1 (0.2, -0.2, -0.3 m "
                "in the platform frame) at z = -0.2000 m outside [0.0408, 2.4592] m"
            )
            assert err.reason.endswith(" at the target")

    run(scenario())


def test_a_goto_whose_cable_would_cross_a_box_is_refused_naming_the_cable() -> None:
    """A crate on the floor near the +x+y lower anchor: at home the cables clear it; a
    goto towards +x puts cable 1 through it."""
    crate = {"name": "crate", "min": [0.9, -0.5, 0.0], "max": [1.5, 0.5, 0.6]}

    async def scenario() -> None:
        async with Stack(config_for("cia402", environment={"boxes": [crate]})) as stack:
            await stack.enable()
            target = _home(stack.config, dx=0.5, dz=-0.5)
            err = await _refused(stack, stack.planner.command("goto", {"pose": target}))
            assert err.details["limit"] == "environment"
            assert "cable 1 crosses box 'crate'" in err.reason

    run(scenario())


def test_the_monitor_brakes_a_body_enabled_into_a_box() -> None:
    """The platform placed 0.12 m below home, its reference point well inside the box,
    its bottom face 2 cm into the bench under it (no corner in it: the separating axis
    test finds it): the first cycles after enable brake, naming the body and the box."""

    async def scenario() -> None:
        config = config_for("cia402", environment=BENCH)
        stack = Stack(config)
        stack.plant.reset(_home(config, dz=-0.12))
        async with stack:
            service = stack.service
            with contextlib.suppress(CommandError):  # braked within it: the state says why
                await service.command("enable", {})
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 5.0)
            fault = service.machine.fault
            assert fault is not None and fault.trigger is Trigger.POSE_LIMIT, fault
            assert fault.message.startswith("the platform body crosses box 'bench'")

    run(scenario())
