"""A docking fixture: the platform starts resting on it, its cables slack.

A real robot is built, or parked, with the platform on a support and its cables slack or
at unknown tension; pretension must wind them in and take the load over without moving
the platform.  The fixture is a stiff, damped, unilateral contact at a pose of the robot
file: while it pushes the platform up (the vertical part of its spring-damper force is
positive) it also locates it in the other five directions (a cone or pins), and lifted
off it exerts nothing.  It acts at the reference point p, with

    F = -K (p - p_f) - C v,   tau = -K_r theta - C_r omega,   theta = log(R R_f^T)

(force, torque about p; world frame), applied only while F_z > 0.
"""

from __future__ import annotations

from collections.abc import Sequence

from cdpr import ConfigError, Pose, Robot
from cdpr.description import NonNegativeFloat, PositiveFloat, StrictModel
from cdpr.so3 import quat4_to_rotvec, quat_mul4

Wrench = tuple[float, float, float, float, float, float]


class FixtureConfig(StrictModel):
    """`sim.plant.fixture`: the platform starts at rest on a docking fixture at the robot
    file's pose `pose` ("home" or a name under `poses:`), every cable `slack_m` m longer
    than taut (one value, or one per cable) and carrying nothing, the drives' commands
    zero.  stiffness / damping: N/m and N s/m of the contact; rotational_*: N m/rad and
    N m s/rad."""

    pose: str = "home"  # the robot file's pose it rests at: "home" or a name under poses
    slack_m: NonNegativeFloat | list[NonNegativeFloat] = 0.05  # m: one, or one per cable
    stiffness: PositiveFloat = 1.0e6  # N/m, of the contact
    damping: NonNegativeFloat = 5.0e3  # N s/m, of the contact
    rotational_stiffness: PositiveFloat = 1.0e4  # N m/rad, against turning off the pose
    rotational_damping: NonNegativeFloat = 100.0  # N m s/rad, against turning

    def resting_pose(self, robot: Robot) -> Pose:
        """The fixture's pose in `robot` (ConfigError naming the key for an unknown one)."""
        pose = robot.poses.get(self.pose)
        if pose is None:
            known = ", ".join(robot.poses)
            raise ConfigError(f"sim.plant.fixture.pose: no pose {self.pose!r} (poses: {known})")
        return pose

    def slack_for(self, n: int) -> list[float]:
        """slack_m per cable (ConfigError on a wrong count)."""
        if not isinstance(self.slack_m, list):
            return [float(self.slack_m)] * n
        if len(self.slack_m) != n:
            raise ConfigError(
                f"sim.plant.fixture.slack_m: {len(self.slack_m)} entries for {n} cables"
            )
        return [float(s) for s in self.slack_m]


class Fixture:
    """The contact of `config` at `pose` (the true robot's)."""

    def __init__(self, config: FixtureConfig, pose: Pose) -> None:
        self.config = config
        self.position = pose.position_tuple
        w, x, y, z = pose.quaternion_tuple
        self._inverse = (w, -x, -y, -z)

    def wrench(
        self,
        position: Sequence[float],
        quaternion: Sequence[float],
        velocity: Sequence[float],
        omega: Sequence[float],
    ) -> Wrench | None:
        """The contact's wrench on the platform at p (None: lifted off, no contact)."""
        c = self.config
        k, d = c.stiffness, c.damping
        fz = -k * (position[2] - self.position[2]) - d * velocity[2]
        if fz <= 0.0:
            return None
        fx = -k * (position[0] - self.position[0]) - d * velocity[0]
        fy = -k * (position[1] - self.position[1]) - d * velocity[1]
        theta = quat4_to_rotvec(*quat_mul4(*quaternion, *self._inverse))
        kr, dr = c.rotational_stiffness, c.rotational_damping
        tx, ty, tz = (-kr * a - dr * w for a, w in zip(theta, omega, strict=True))
        return fx, fy, fz, tx, ty, tz

