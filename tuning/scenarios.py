"""The standard trajectory set for closed-loop results (issue: controller, reference8).

- figure_eight: a horizontal figure-8 (Gerono lemniscate) about the home pose at
  0.5 m/s peak, with a +-10 deg roll/pitch wobble, eased in and out of rest;
- vertical_lift: a 1 m rest-to-rest lift along z through the home position;
- edge_move: a fast rest-to-rest move across the workspace near its edge.

Each is a cdpr Trajectory starting at t = 0 at rest at `start_pose(...)`; the same
set drives tests, bench/controller.py and the demo.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from cdpr import Pose, Robot
from cdpr.trajectory import Trajectory, Waypoint

SPACING = 0.05  # s between the waypoints sampled from an analytic path


def figure_eight(robot: Robot, peak_speed: float = 0.5, wobble_deg: float = 10.0) -> Trajectory:
    """One lap of x = A sin(s), y = A sin(s) cos(s) about home, tilt wobbling +-wobble."""
    A = 0.4  # m
    # |dp/ds| peaks at s = 0: sqrt(A^2 + A^2) -> lap speed ds/dt = peak / (A sqrt 2)
    rate = peak_speed / (A * math.sqrt(2.0))
    wobble = math.radians(wobble_deg)
    centre = robot.home.position

    def pose(s: float) -> Pose:
        offset = (A * math.sin(s), A * math.sin(s) * math.cos(s), 0.0)
        tilt = (wobble * math.sin(s), wobble * math.sin(2.0 * s), 0.0)
        return Pose.from_rotvec(centre + np.array(offset), tilt)

    return _eased(pose, 2.0 * math.pi, rate, ease=1.5)


def vertical_lift(robot: Robot, height: float = 1.0, duration: float = 4.0) -> Trajectory:
    """Rest to rest from home - height/2 to home + height/2 along z (minimum jerk)."""
    low = robot.home.position - np.array((0.0, 0.0, height / 2))
    high = robot.home.position + np.array((0.0, 0.0, height / 2))
    q = robot.home.quaternion
    return Trajectory([Waypoint(0.0, Pose(low, q)), Waypoint(duration, Pose(high, q))])


def edge_move(robot: Robot, duration: float = 2.3) -> Trajectory:
    """Rest to rest across the workspace 0.55 m from the centre line, low and with a
    turn: 1.2 m in `duration` s.  Two waypoints make a minimum-jerk move, whose peak
    speed is 15/8 of the mean: 0.98 m/s at the default, inside the trajectory limit
    linear_speed of 1 m/s (the default's, and the reference configs'), so that the
    daemon accepts it."""
    home = robot.home.position
    start = Pose.from_rotvec(home + np.array((-0.6, 0.55, -0.35)), (0.0, 0.0, -0.15))
    end = Pose.from_rotvec(home + np.array((0.6, 0.55, -0.35)), (0.0, 0.0, 0.15))
    return Trajectory([Waypoint(0.0, start), Waypoint(duration, end)])


def rotation_wobble(
    robot: Robot, amplitude_deg: float = 12.0, rate: float = 4.0, laps: float = 3.0
) -> Trajectory:
    """The platform turning about all three axes at home, out of phase and at three
    rates (s, 1.5 s, 0.75 s with ds/dt = `rate`), for `laps` laps of s: angular
    accelerations of a few rad/s^2 about every axis, which reveal the inertia."""
    a = math.radians(amplitude_deg)
    centre = robot.home.position

    def pose(s: float) -> Pose:
        return Pose.from_rotvec(centre, (a * math.sin(s), a * math.sin(1.5 * s),
                                         a * math.sin(0.75 * s)))  # fmt: skip

    return _eased(pose, 2.0 * math.pi * laps, rate, ease=1.0)


STANDARD_SET: dict[str, Callable[[Robot], Trajectory]] = {
    "figure_eight": figure_eight,
    "vertical_lift": vertical_lift,
    "edge_move": edge_move,
}


def start_pose(trajectory: Trajectory) -> Pose:
    """Where the trajectory begins (at rest)."""
    return trajectory.sample(trajectory.start_time).pose


def _eased(path: Callable[[float], Pose], length: float, rate: float, ease: float) -> Trajectory:
    """Waypoints of path(s), s from 0 to `length`, at ds/dt = rate except over the first
    and last `ease` seconds, where the rate ramps smoothly from and to zero."""
    # s(t): rate ramps as the quintic smoothstep over `ease` seconds; each ramp covers
    # rate * ease / 2 of the path
    cruise = (length - rate * ease) / rate
    if cruise < 0.0:
        raise ValueError("path too short for its easing")
    total = 2.0 * ease + cruise

    def s_of(t: float) -> float:
        if t < ease:
            return rate * ease * _smoothstep_integral(t / ease)
        if t <= ease + cruise:
            return rate * ease / 2.0 + rate * (t - ease)
        return length - rate * ease * _smoothstep_integral((total - t) / ease)

    count = max(2, math.ceil(total / SPACING) + 1)
    times = np.linspace(0.0, total, count)
    return Trajectory([Waypoint(float(t), path(s_of(float(t)))) for t in times])


def _smoothstep_integral(x: float) -> float:
    """Integral from 0 to x of the quintic smoothstep 10u^3 - 15u^4 + 6u^5 (x in [0, 1])."""
    return 2.5 * x**4 - 3.0 * x**5 + x**6
