"""The `cdprd` command line."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from cdpr import ConfigError, Robot


def check_config(path: str) -> int:
    """Validate a robot description and print a readable summary; 0 if it is sound."""
    try:
        robot = Robot.from_yaml(path)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    home = robot.home
    lengths = robot.cable_lengths(home)
    masses = robot.modal_masses(home)
    print(f"robot {robot.name}: {robot.n_cables} cables, platform {robot.platform.mass:g} kg")
    print(
        f"home position {np.round(home.position, 4).tolist()} m, "
        f"quaternion {np.round(home.quaternion, 6).tolist()}"
    )
    print(f"cable lengths at home: {np.round(lengths, 4).tolist()} m")
    shown = ", ".join("inf" if np.isinf(m) else f"{m:.3g}" for m in masses)
    print(f"modal masses at home (Lemma 1, kg): {shown}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cdprd", description="Hardware-interface daemon for cable-driven parallel robots."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check-config", help="validate a robot description file")
    check.add_argument("file", help="robot YAML, e.g. config/robots/reference8.yaml")
    args = parser.parse_args(argv)
    if args.command == "check-config":
        return check_config(args.file)
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
