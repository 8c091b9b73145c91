"""Benchmark of the reference trajectory on config/robots/reference8.yaml.

Prints per-call median and p99 in microseconds of: `Trajectory.sample()` on a
20-waypoint trajectory at 1 kHz cycle times (`sample`), building that trajectory from
its dict form (`parse`), and validating it against the default limits (`validate`);
validating a LONG_WAYPOINTS trajectory (0.1 s apart: 1,000 s of motion, ~110,000
samples) as the daemon validates a client's, wrench set and workspace margin included
(`validate_long`, config/reference8-cia402.yaml); and
planning a hold (`hold`: stop_steps) and a goto home (`goto_moving`) from each of
MOVING_STATES states along a 0.34 m goto with the jerk bounded (the trajectory limits of
config/reference8-cia402.yaml), a third of them in its first phase, where a ramp leads.

    python bench/trajectory.py [--json] [--calls N]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from timing import REFERENCE8, per_call_us, print_timings

from cdpr import Pose, Robot
from cdpr.trajectory import (
    Reference,
    Trajectory,
    TrajectoryLimits,
    Waypoint,
    goto,
    parse_trajectory,
    run_steps,
    stop_steps,
    validate,
)
from daemon.config import load_config
from daemon.service.planner import validate_as_the_daemon

CONFIGS = Path(__file__).resolve().parent.parent / "config"
MOVING_STATES = 30  # along the goto the hold and goto_moving plans start from
LONG_WAYPOINTS = 10_000  # the default max_waypoints


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


def long_trajectory(robot: Robot, n_waypoints: int = LONG_WAYPOINTS) -> Trajectory:
    """n waypoints 0.1 s apart on a 3 cm circle about home, once a minute, with a slow
    yaw (bench/flood.py's long mix, as arrays)."""
    angle = 2.0 * np.pi * np.arange(n_waypoints) * 0.1 / 60.0
    positions = robot.home.position + 0.03 * np.column_stack(
        [np.sin(angle), 1.0 - np.cos(angle), np.zeros(n_waypoints)]
    )
    yaw = 0.05 * np.sin(angle)
    quaternions = np.column_stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)])
    return Trajectory.through(0.1 * np.arange(n_waypoints), positions, quaternions)


def sample_us(trajectory: Trajectory, calls: int, rate_hz: float = 1000.0) -> dict[str, float]:
    """Per-call time of trajectory.sample() at successive control-cycle times."""
    times = (trajectory.start_time + (np.arange(calls) / rate_hz) % trajectory.duration).tolist()
    return per_call_us(lambda i: trajectory.sample(times[i % len(times)]), calls)


def moving_states(robot: Robot, limits: TrajectoryLimits) -> list[Reference]:
    """MOVING_STATES reference states along a goto 0.3 m in x and 0.15 m in z across home."""
    home = robot.home
    side = np.array([0.15, 0.0, 0.075])
    behind, ahead = Pose(home.position - side), Pose(home.position + side)
    flight = goto(Reference(behind, np.zeros(6), np.zeros(6)), ahead, limits)
    times = np.linspace(0.0, flight.end_time, MOVING_STATES + 2)[1:-1]
    return [flight.sample(float(t)) for t in times]


def results(calls: int) -> dict[str, dict[str, float]]:
    robot = Robot.from_yaml(REFERENCE8)
    trajectory = reference_trajectory(robot)
    limits = TrajectoryLimits()
    data = trajectory.as_dict()
    config = load_config(CONFIGS / "reference8-cia402.yaml")
    shipped = config.trajectory
    states = moving_states(robot, shipped)
    long = long_trajectory(robot)
    home = Pose(robot.home.position)
    return {
        "sample": sample_us(trajectory, calls),
        "parse": per_call_us(lambda i: parse_trajectory(data, limits), max(calls // 100, 20)),
        "validate": per_call_us(lambda i: validate(trajectory, robot, limits), 5),
        "validate_long": per_call_us(lambda i: validate_as_the_daemon(long, config), 3, 1),
        "hold": per_call_us(
            lambda i: run_steps(stop_steps(states[i % MOVING_STATES], shipped)),
            3 * MOVING_STATES,
            warm_up=MOVING_STATES,
        ),
        "goto_moving": per_call_us(
            lambda i: goto(states[i % MOVING_STATES], home, shipped),
            3 * MOVING_STATES,
            warm_up=MOVING_STATES,
        ),
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
