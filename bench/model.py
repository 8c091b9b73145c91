"""Benchmark of the model core on config/robots/reference8.yaml.

Prints per-call median and p99 in microseconds of: lengths + Jacobian
(`lengths_jacobian`), c (`bias_accel`), forward kinematics warm-started after a
1 mm / 0.5 deg move (`fk_warm`), and M with mu (`dynamics`).

    python bench/model.py [--json] [--calls N]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from timing import REFERENCE8, per_call_us, print_timings

from cdpr import Pose, Robot, retract


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--calls", type=int, default=20000, help="timed calls per item")
    args = parser.parse_args(argv)

    robot = Robot.from_yaml(REFERENCE8)
    rng = np.random.default_rng(1)
    n = 256
    poses = [
        Pose.from_rotvec(
            robot.home.position + rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.15, 0.15, 3)
        )
        for _ in range(n)
    ]
    twists = [rng.normal(0.0, 0.3, 6) for _ in range(n)]
    # the previous cycle's pose: 1 mm and 0.5 deg away in random directions
    guesses = []
    for pose in poses:
        dp = rng.normal(size=3)
        dw = rng.normal(size=3)
        step = np.concatenate(
            [1e-3 * dp / np.linalg.norm(dp), np.deg2rad(0.5) * dw / np.linalg.norm(dw)]
        )
        guesses.append(retract(pose, step))
    lengths = [robot.cable_lengths(p) for p in poses]

    fk_iterations = [robot.forward_kinematics(lengths[i], guesses[i]).iterations for i in range(n)]
    results = {
        "lengths_jacobian": per_call_us(
            lambda i: robot.lengths_and_jacobian(poses[i % n]), args.calls
        ),
        "bias_accel": per_call_us(
            lambda i: robot.bias_accel(poses[i % n], twists[i % n]), args.calls
        ),
        "fk_warm": per_call_us(
            lambda i: robot.forward_kinematics(lengths[i % n], guesses[i % n]), args.calls
        ),
        "dynamics": per_call_us(lambda i: robot.dynamics(poses[i % n], twists[i % n]), args.calls),
    }
    results["fk_warm"]["iterations_median"] = float(np.median(fk_iterations))
    if args.json:
        print(json.dumps(results))
    else:
        print_timings(results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
