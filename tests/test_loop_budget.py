"""One big input must not stall the control loop (issue 22, item 4): a 10,000-waypoint
trajectory reaching a holding robot in-process (daemon + simulator over the loop bus).
A loop held up for the drives' watchdog brakes them; the bound here is in control
cycles, counted by the cycle's own timer (periods elapsed between two ticks), never in
wall-clock time."""

from __future__ import annotations

import asyncio
import math

import pytest

from cdpr.trajectory import Trajectory, parse_trajectory
from daemon.safety import SafetyState
from tests.daemon_stack import Stack, config_for

pytestmark = pytest.mark.timeout(120)


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 100))


def circle(n: int) -> Trajectory:
    """n waypoints 10 ms apart: a 5 cm circle about home every 10 s, home to home."""
    loops = max(1, round(n / 1000))
    waypoints = []
    for k in range(n):
        angle = 2.0 * math.pi * loops * k / (n - 1)
        waypoints.append(
            {
                "t": 0.01 * k,
                "position": [0.05 * math.sin(angle), 0.05 * (1.0 - math.cos(angle)), 1.25],
                "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
            }
        )
    waypoints[-1]["position"] = [0.0, 0.0, 1.25]
    return parse_trajectory({"version": 1, "waypoints": waypoints})


class LongestStall:
    """The most control periods that passed between two ticks of the service's timer."""

    def __init__(self, stack: Stack) -> None:
        timer = stack.service._timer
        assert timer is not None
        read = timer.expirations
        self.periods = 0

        def counting() -> int:
            n = read()
            self.periods = max(self.periods, n)
            return n

        timer.expirations = counting  # type: ignore[method-assign]


def watchdog_periods(stack: Stack) -> int:
    """The drives' watchdog in control periods: a longer stall brakes them."""
    config = stack.config
    return math.floor(config.drives.watchdog_timeout * config.controller.rate_hz)


@pytest.mark.slow
def test_a_10000_waypoint_trajectory_reaches_a_holding_robot_without_a_stall() -> None:
    config = config_for("cia402")
    trajectory = circle(config.trajectory.max_waypoints)  # as the parse thread makes it
    assert len(trajectory.waypoints) == 10_000

    async def scenario() -> None:
        async with Stack(config) as stack:
            await stack.enable()
            await asyncio.sleep(0.2)
            stall = LongestStall(stack)
            service = stack.service
            reply = await service.submit_trajectory(trajectory, None)  # validate, plan, run
            assert reply["accepted"] and reply["duration"] >= trajectory.duration
            await asyncio.sleep(0.3)
            assert service.machine.state is SafetyState.TRACKING, service.machine.fault
            # shifting and blending 10,000 waypoints on the loop stalled it ~100 periods
            assert stall.periods < watchdog_periods(stack), f"{stall.periods} periods"

    run(scenario())
