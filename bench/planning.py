"""Benchmark of path timing (cdpr.path.timing): how long planning takes, and how close
its durations come to an independent time-optimal bound.

    python bench/planning.py [--json] [--runs N] [--no-ratios]

- plan_ms.path_100: parse and time a 100-pose JSON path (a climbing square spiral,
  blended corners, 10 m) on config/reference8-cia402.yaml, median of N runs;
  plan_ms.gcode_2000: the same for a 2,000-line G-code file (a zig-zag, 1 cm blends).
- duration_ratio.<path>: TOPP-RA's duration (1 cm grid) / the optimum of the convex
  formulation of tuning.convex_timing (Verscheure et al. 2009, tensions as variables,
  2 mm grid), both with a 5 N tension margin on reference8 without the winches' damping
  (which the convex form cannot hold): vertical_lift and edge_move (the standard
  trajectories' end poses, rest to rest), blended_corner (two sides of a square, 5 cm
  blend).  Within 3 % is the goal.
"""

from __future__ import annotations

import argparse
import copy
import json
import time

import numpy as np
from timing import REFERENCE8

from cdpr.path import Path, PathPoint, parse_gcode, parse_path
from cdpr.path.timing import Timing, time_path
from cdpr.pose import Pose
from daemon.config import load_config

CONFIG = REFERENCE8.parent.parent / "reference8-cia402.yaml"
MARGIN = 5.0


def spiral(n: int) -> dict:
    q = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    poses = [{"position": [0.0, 0.0, 1.0], "quaternion": q}]
    for k in range(1, n):
        x, y = 0.25 * ((k % 4) in (1, 2)), 0.25 * ((k % 4) >= 2)
        poses.append({"position": [x, y, 1.0 + 0.005 * k], "blend": 0.03})
    return {"poses": poses}


def zigzag(lines: int) -> str:
    rows = ["G21 G90 F30000"]
    rows += [f"G1 X{100 * (k % 2)} Y{-100 + 0.1 * k:.1f}" for k in range(lines - 1)]
    return "\n".join(rows)


def plan_ms(config, runs: int) -> dict[str, float]:
    robot, limits = config.robot, config.trajectory
    body, program = spiral(100), zigzag(2000)
    out = {}
    for name, make in (
        ("path_100", lambda: parse_path(body, limits)),
        ("gcode_2000", lambda: parse_gcode(program, robot.home, 0.01, limits)),
    ):
        times = []
        for _ in range(runs):
            began = time.perf_counter()
            time_path(make(), robot, limits, Timing(margin=MARGIN))
            times.append(time.perf_counter() - began)
        out[name] = round(1e3 * float(np.median(times)), 1)
    return out


def duration_ratios(config) -> dict[str, float]:
    from tuning.convex_timing import convex_duration

    robot = copy.deepcopy(config.robot)
    robot.k0 = np.zeros_like(robot.k0)
    limits, home = config.trajectory, robot.home

    def at(dx: float, dy: float, dz: float, turn: float = 0.0) -> Pose:
        return Pose.from_rotvec(home.position + np.array([dx, dy, dz]), [0.0, 0.0, turn])

    cases = {
        "vertical_lift": [at(0, 0, -0.5), at(0, 0, 0.5)],
        "edge_move": [at(-0.6, 0.55, -0.35, -0.15), at(0.6, 0.55, -0.35, 0.15)],
        "blended_corner": [at(0, 0, 0), at(0.3, 0, 0), at(0.3, 0.3, 0.1)],
    }
    out = {}
    for name, poses in cases.items():
        blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
        path = Path(tuple(PathPoint(p, blend=r) for p, r in zip(poses, blends, strict=True)))
        planned = time_path(path, robot, limits, Timing(margin=MARGIN)).duration
        optimum = convex_duration(poses, blends, robot, limits, MARGIN, step=0.002)
        out[name] = round(planned / optimum, 4)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--no-ratios", action="store_true", help="skip the convex bounds")
    args = parser.parse_args()
    config = load_config(CONFIG)
    result = {"plan_ms": plan_ms(config, args.runs)}
    if not args.no_ratios:
        result["duration_ratio"] = duration_ratios(config)
    if args.json:
        print(json.dumps(result))
    else:
        for group, values in result.items():
            for key, value in values.items():
                print(f"{group}.{key}: {value}")


if __name__ == "__main__":
    main()
