"""Benchmark of the reference trajectory on config/robots/reference8.yaml.

Prints per-call median and p99 in microseconds of: `Trajectory.sample()` on a
20-waypoint trajectory at 1 kHz cycle times (`sample`), building that trajectory from
its dict form (`parse`), and validating it against the default limits (`validate`).

    python bench/trajectory.py [--json] [--calls N]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from timing import REFERENCE8, per_call_us, print_timings

from cdpr import Pose, Robot
from cdpr.trajectory import Trajectory, TrajectoryLimits, Waypoint, parse_trajectory, validate


def reference_trajectory(robot: Robot, n_waypoints: int = 20, seed: int = 1) -> Trajectory:
    """n waypoints 1 s apart within 0.2 m and 0.1 rad of home: valid for the default limits."""
    rng = np.random.default_rng(seed)
    return Trajectory(
        [
            Waypoint(
                float(k),
                Pose.from_rotvec(
                    robot.home.position + rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)
                ),
            )
            for k in range(n_waypoints)
        ]
    )


def sample_us(trajectory: Trajectory, calls: int, rate_hz: float = 1000.0) -> dict[str, float]:
    """Per-call time of trajectory.sample() at successive control-cycle times."""
    times = (trajectory.start_time + (np.arange(calls) / rate_hz) % trajectory.duration).tolist()
    return per_call_us(lambda i: trajectory.sample(times[i % len(times)]), calls)


def results(calls: int) -> dict[str, dict[str, float]]:
    robot = Robot.from_yaml(REFERENCE8)
    trajectory = reference_trajectory(robot)
    limits = TrajectoryLimits()
    data = trajectory.as_dict()
    return {
        "sample": sample_us(trajectory, calls),
        "parse": per_call_us(lambda i: parse_trajectory(data, limits), max(calls // 100, 20)),
        "validate": per_call_us(lambda i: validate(trajectory, robot, limits), 5),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--calls", type=int, default=20000, help="timed sample() calls")
    args = parser.parse_args(argv)
    out = results(args.calls)
    if args.json:
        print(json.dumps(out))
    else:
        print_timings(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
