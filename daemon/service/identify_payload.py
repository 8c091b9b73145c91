"""identify-payload: hold a few poses, estimate the platform's mass and centre of mass
from the forces that hold it there (cdpr.payload.static_fit), apply it if asked
(DESIGN §15 step 6).

Runs where the planner runs (the companion): each pose is a goto; once the robot holds
it (HOLD again) and SETTLE s have passed, SAMPLES state snapshots SPACING s apart give
the measured pose and the drives' forces.  At rest the forces along the measured cables
balance the platform's weight whatever the controller's state, so the estimate does not
depend on the model it is flying with.  The poses: where the robot is, and that pose
tilted by +-TILT about the platform's x and y axes (the tilts reveal the centre of mass
along the platform's z axis, which no upright pose shows).  The robot returns to where
it was.  The whole procedure is one motion, its client's (daemon.service.motion): a
request that replaces it (preempt, or a hold) stops it at its next step ("preempted").
"""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr.payload import static_fit
from cdpr.pose import Pose
from daemon.service.api import CommandError
from daemon.service.safety import SafetyState

if TYPE_CHECKING:
    from daemon.service.motion import Motion
    from daemon.service.planner import Planner

TILT = math.radians(8.0)  # rad about each platform axis (within the usual tilt limits)
SETTLE = 1.0  # s after a goto ends before sampling
SAMPLES = 10  # state snapshots per pose
SPACING = 0.05  # s between two
HOLD_TIMEOUT = 30.0  # s a goto may take to end (HOLD again)


def identification_poses(start: Pose, tilt: float = TILT) -> list[Pose]:
    """`start`, then `start` tilted by +-tilt about its own x and y axes."""
    turns = [(tilt, 0.0, 0.0), (-tilt, 0.0, 0.0), (0.0, tilt, 0.0), (0.0, -tilt, 0.0)]
    R = start.rotation
    return [start] + [
        Pose.from_matrix(start.position, R @ Pose.from_rotvec(np.zeros(3), turn).rotation)
        for turn in turns
    ]


async def identify_payload(
    planner: Planner, args: dict[str, Any], motion: Motion
) -> dict[str, Any]:
    """The identify_payload command, run as `motion`: the estimate, its standard
    deviations (null for a component the poses did not reveal), and whether it was
    applied."""
    link = planner.link
    start = (await _measured(planner, motion))[0]
    samples: list[tuple[Pose, list[float]]] = []
    for pose in identification_poses(start):
        await planner.fly_to(pose, motion)
        await _held(planner, motion)
        await asyncio.sleep(SETTLE)
        for _ in range(SAMPLES):
            samples.append(await _measured(planner, motion))
            await asyncio.sleep(SPACING)
    await planner.fly_to(start, motion)
    await _held(planner, motion)
    fit = static_fit(planner.robot, samples)
    result: dict[str, Any] = {
        "mass": fit.mass,
        "center_of_mass": list(fit.center_of_mass),
        "mass_std": fit.mass_std,
        "center_of_mass_std": list(fit.center_of_mass_std),  # inf: sent as null
        "residual_rms": fit.residual_rms,
        "poses": len(samples) // SAMPLES,
        "applied": False,
    }
    if args.get("apply"):
        planner.motions.owns(motion)
        await link.command("payload", {"mass": fit.mass, "center_of_mass": fit.center_of_mass})
        result["applied"] = True
    return result


async def _held(planner: Planner, motion: Motion) -> None:
    """Until the robot holds its pose again after a goto (CommandError if it stopped
    moving, e.g. braked, another motion replaced `motion`, or the goto did not end)."""
    waited = 0.0
    while planner.link.safety_state != SafetyState.HOLD.value:
        _require_moving(planner, motion)
        if waited > HOLD_TIMEOUT:
            raise CommandError("internal", f"a goto did not end within {HOLD_TIMEOUT:g} s")
        await asyncio.sleep(SPACING)
        waited += SPACING


def _require_moving(planner: Planner, motion: Motion) -> None:
    planner.motions.owns(motion)
    state = planner.link.safety_state
    if state not in (SafetyState.HOLD.value, SafetyState.TRACKING.value):
        raise CommandError("invalid_state", f"identify_payload stopped: the robot is {state}")


async def _measured(planner: Planner, motion: Motion) -> tuple[Pose, list[float]]:
    """The measured pose and the drives' forces of the state (the first cycle's may
    still be on its way just after enable)."""
    for _ in range(round(1.0 / SPACING)):
        _require_moving(planner, motion)
        state = planner.link.state()
        pose, forces = state.get("pose"), state.get("forces")
        if pose is not None and forces is not None:
            break
        await asyncio.sleep(SPACING)
    else:
        raise CommandError("invalid_state", "no measured pose and forces in the state")
    q = pose["quaternion"]
    return Pose(pose["position"], (q["w"], q["x"], q["y"], q["z"])), list(forces)
