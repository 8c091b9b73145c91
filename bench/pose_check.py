"""The runtime pose check's cost per control cycle (cdpr.pose_limits, cdpr.body).

The safety monitor asks PoseLimits.violation of every measured pose.  Timed on
config/reference8-cia402.yaml (min over repeats, us per check): the reference point and
the tilt alone (the check before the body), with the platform's corners clear of every
face, with its corners near a face, with a floor and a wall, and with a table the lower
cables pass over (a slab test per cable each cycle).

    python bench/pose_check.py [--json] [--calls N]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import timeit
from pathlib import Path

from cdpr import Pose
from cdpr.body import Box, Environment, Plane
from daemon.config import load_config

CONFIG = Path(__file__).resolve().parent.parent / "config" / "reference8-cia402.yaml"


def cases() -> dict[str, tuple]:
    """name: (PoseLimits, pose), each pose inside its limits."""
    limits = load_config(CONFIG).pose_limits
    anchors = limits.environment.anchors
    middle = Pose.from_rotvec((0.1, 0.05, 1.2), (0.05, 0.02, 0.1))
    near_face = Pose.from_rotvec((1.2, 0.05, 1.2), (0.05, 0.02, 0.1))
    planes = (Plane("floor", (0.0, 0.0, 1.0), 0.0), Plane("wall", (-1.0, 0.0, 0.0), -1.45))
    table = Box("table", (0.9, -0.5, 0.0), (1.5, 0.5, 0.6))
    return {
        "reference_point_only": (dataclasses.replace(limits, body=None), middle),
        "body_clear": (limits, middle),
        "body_near_face": (limits, near_face),
        "two_planes": (
            dataclasses.replace(limits, environment=Environment(planes, (), anchors)),
            middle,
        ),
        "planes_and_table": (
            dataclasses.replace(limits, environment=Environment(planes, (table,), anchors)),
            middle,
        ),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--calls", type=int, default=5000, help="checks per repeat")
    args = parser.parse_args(argv)
    results = {}
    for name, (limits, pose) in cases().items():
        assert limits.violation(pose) is None, name
        position, quaternion = pose.position_tuple, pose.quaternion_tuple

        def check(limits=limits, position=position, quaternion=quaternion) -> None:
            limits.violation(Pose._from_unit(position, quaternion))  # as fresh as FK's

        best = min(timeit.repeat(check, number=args.calls, repeat=7))
        results[name] = round(best / args.calls * 1e6, 2)
    if args.json:
        print(json.dumps(results))
    else:
        for name, us in results.items():
            print(f"{name:22s} {us:8.2f} us per check")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
