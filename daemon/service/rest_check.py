"""Is the platform where we think it is?  The statics of a pose against the tensions the
drives measure at rest (DESIGN §19).

Stored length offsets are data from disk, and `home` is told a pose by an operator:
neither is a fact about the robot.  Lengths alone cannot tell a wrong zero from a
platform elsewhere (offsets shifted together as a pose shift fit that pose exactly), but
the cables' tensions can: at rest they balance the platform's weight at the pose where it
really is, Lambda(eta)^T t + mu(eta, 0) = 0.  The same tensions at another pose leave a
net wrench, roughly the internal forces times the change of the cables' directions: on
the reference robot (eight cables at ~300 N) a pose 50 mm too high leaves 44 N, one
300 mm too high 267 N, when the platform weighs 98 N.  A payload that is neither in the
robot file nor estimated leaves its weight unbalanced too: the refusal names both.

`judge` compares the residual with safety.rest_force (N) and safety.rest_torque (N m,
about the reference point) and returns the refusal, naming the check and the figures.
The tensions are the drives' own measurement while they hold their positions (f = -t;
drivers.base.ActuatorDriver.measured_forces), which also carries the drums' static
friction: the tolerances must cover it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cdpr.pose import Pose
from cdpr.robot import Robot


@dataclass(frozen=True)
class RestResidual:
    """The net force (N, world frame) and torque about the reference point (N m) that
    the measured tensions leave at a pose."""

    force: np.ndarray
    torque: np.ndarray

    def text(self) -> str:
        # rounded first, so that a rounding error prints as 0.0, not -0.0
        f, m = np.round(self.force, 1) + 0.0, np.round(self.torque, 2) + 0.0
        return (
            f"net force [{f[0]:.1f}, {f[1]:.1f}, {f[2]:.1f}] N (|{np.linalg.norm(f):.1f}| N), "
            f"torque [{m[0]:.2f}, {m[1]:.2f}, {m[2]:.2f}] N m (|{np.linalg.norm(m):.2f}| N m)"
        )


def rest_residual(robot: Robot, pose: Pose, forces: Sequence[float]) -> RestResidual:
    """What the drives' measured forces (N along +l) leave unbalanced with the platform
    at rest at `pose`: Lambda^T t + mu(pose, 0), t = -f."""
    tensions = -np.asarray(forces, dtype=float)
    wrench = robot.jacobian(pose).T @ tensions + robot.bias_wrench(pose, np.zeros(6))
    return RestResidual(wrench[:3], wrench[3:])


def judge(
    robot: Robot,
    pose: Pose,
    forces: Sequence[float],
    max_force: float,
    max_torque: float,
) -> tuple[RestResidual, str | None]:
    """The residual at `pose`, and why the platform cannot be resting there (None: it
    can, within `max_force` N and `max_torque` N m)."""
    residual = rest_residual(robot, pose, forces)
    force = float(np.linalg.norm(residual.force))
    torque = float(np.linalg.norm(residual.torque))
    if np.isfinite(force) and np.isfinite(torque) and force <= max_force and torque <= max_torque:
        return residual, None
    return residual, (
        f"the tensions the drives measure at rest do not hold the platform there: "
        f"{residual.text()} (allowed {max_force:g} N, {max_torque:g} N m: "
        "safety.rest_force, safety.rest_torque)"
    )
