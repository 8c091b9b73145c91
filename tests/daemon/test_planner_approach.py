"""The planner's approach into a trajectory from a reference accelerating at its
jerk-bounded limit: the ramp that leads it (cdpr.trajectory.transitions) is validated
with the rest of the approach, not only its first segment."""

from __future__ import annotations

import asyncio
from collections.abc import Generator
from typing import Any

import numpy as np

from cdpr import Pose
from cdpr.trajectory import Reference, Trajectory, Waypoint, approach, goto, run_steps
from daemon.service.planner import Planner
from tests.daemon_stack import config_for


class StillLink:
    """A CoreLink whose reference is one given state (the core's clock stopped at NOW):
    what the planner hands the core is kept in `followed`."""

    NOW = 100.0

    def __init__(self, state: Reference) -> None:
        self.reference = state
        self.followed: list[Trajectory] = []

    def now(self) -> float:
        return self.NOW

    @property
    def safety_state(self) -> str:
        return "tracking"

    def state(self) -> dict[str, Any]:
        return {}

    def subscribe(self, sink: Any) -> None:
        pass

    async def command_keeping(self, name: str, args: dict[str, Any], leases: Any) -> Any:
        raise AssertionError("no core command in this test")

    async def reference_at(self, t: float) -> tuple[Reference, int]:
        return self.reference, 0

    async def run_steps(self, steps: Generator[Any, None, Any]) -> Any:
        return run_steps(steps)

    async def follow(self, trajectory: Trajectory, version: int, what: str) -> dict[str, Any]:
        self.followed.append(trajectory)
        return {"accepted": True, "end": trajectory.end_time}


def test_an_approach_led_by_a_ramp_is_validated_over_every_lead_segment() -> None:
    config = config_for("cia402")  # the jerk bounded, as the configs ship
    limits, home = config.trajectory, config.robot.home
    behind = Pose(home.position - np.array([0.15, 0.0, 0.075]), home.quaternion)
    ahead = Pose(home.position + np.array([0.15, 0.0, 0.075]), home.quaternion)
    flight = goto(Reference(behind, np.zeros(6), np.zeros(6)), ahead, limits)
    body = Trajectory([Waypoint(0.0, home), Waypoint(2.0, ahead)])
    # a state of the goto's first phase from which one segment into `body` has no duration
    states = (flight.sample(t) for t in np.linspace(0.0, flight.end_time, 80)[1:-1])
    current = next(s for s in states if approach(s, body, limits, start=0.0).lead_segments > 1)
    link = StillLink(current)
    planner = Planner(config, link)
    checked: list[int | None] = []
    validate = planner._validate

    async def spied(trajectory: Trajectory, what: str, *args: Any) -> None:
        checked.append(args[2] if len(args) > 2 else None)
        await validate(trajectory, what, *args)

    planner._validate = spied  # type: ignore[method-assign]
    asyncio.run(planner.submit_trajectory(body, None))
    (planned,) = link.followed
    assert planned.lead_segments in (2, 3)  # the ramp's one or two segments, then the blend
    assert checked == [None, planned.lead_segments]  # the body whole, then every lead
    assert planned.start_time >= StillLink.NOW
    begins = planned.sample(planned.start_time)  # where the reference is: no jump
    assert np.allclose(begins.pose.position, current.pose.position, atol=1e-12)
    assert np.allclose(begins.twist, current.twist, atol=1e-12)
    assert np.allclose(begins.accel, current.accel, atol=1e-12)
