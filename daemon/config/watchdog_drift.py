"""How far a cable may move before its drive notices that the daemon died.

A CiA 402 drive applies the last torque the daemon sent until its own watchdog fires: the
consumer heartbeat 0x1016 (the host's heartbeat stopped; the host sets no RPDO deadline,
drivers.cia402.profile), after the detection time t (DrivePlan.detection).  Per
drive k, the bound on its cable's motion over t is

    s_k = 0.5 a_k t^2 + v_k t,   a_k = force_max_k / (m0_k + m)

with v_k the fastest cable k moves within the trajectory limits (cable_speed_bounds), and
a_k the acceleration of that cable when its last torque is off balance by the whole
force_max_k, driving its winch (m0_k, reflected to the cable) and the platform (mass m)
along the cable while the other drives' last torques carry the load.  What the drive's
quick stop ramp (0x6085) adds after it noticed is not included.
"""

from __future__ import annotations

from dataclasses import dataclass

from cdpr import ConfigError, Robot
from cdpr.trajectory import TrajectoryLimits, cable_speed_bounds

FORMULA = "s = 0.5 a t^2 + v t, a = force_max / (m0 + platform mass)"


@dataclass(frozen=True)
class DriftBound:
    """One drive's bound: cable, node, detection time t (s), a (m/s^2), v (m/s)."""

    cable: int
    node: int
    detection: float
    accel: float
    speed: float

    @property
    def drift(self) -> float:
        """The bound s (m)."""
        t = self.detection
        return 0.5 * self.accel * t * t + self.speed * t

    def text(self) -> str:
        t_ms = self.detection * 1e3
        return (
            f"cable {self.cable} (node {self.node}): {self.drift * 1e3:.1f} mm = 0.5 x "
            f"{self.accel:.3g} m/s^2 x ({t_ms:g} ms)^2 + {self.speed:.3g} m/s x {t_ms:g} ms"
        )


def drift_bounds(
    robot: Robot, nodes: list[int], limits: TrajectoryLimits, detection: float
) -> list[DriftBound]:
    """Every drive's bound (module docstring) for a detection time of `detection` s."""
    mass = robot.platform.mass
    speeds = cable_speed_bounds(robot, limits)
    return [
        DriftBound(k, node, detection, actuator.force_max / (actuator.m0 + mass), speeds[k])
        for k, (node, actuator) in enumerate(zip(nodes, robot.actuators, strict=True))
    ]


def check_drift(bounds: list[DriftBound], limit: float, source: str = "config") -> None:
    """ConfigError naming the first drive whose bound exceeds `limit` (m)."""
    for bound in bounds:
        if bound.drift > limit:
            raise ConfigError(
                f"{source}: safety.max_watchdog_drift: a dead daemon goes unnoticed for "
                f"{bound.detection * 1e3:g} ms, in which {bound.text()} under the last "
                f"torque ({FORMULA}), more than the {limit * 1e3:g} mm allowed: shorten "
                "drives.consumer_heartbeat_time (and host_heartbeat_period), or, where it "
                "is not set, drives.watchdog_timeout"
            )
