"""`cdprd plan`: a path timed within the cables' tensions (cdpr.path.timing), checked by
the daemon's own validation, printed, and saved as a trajectory `cdprd send` flies.

    cdprd plan FILE --config CFG [--blend M] [--margin N] [--output TRAJ] [--json]

FILE is a path in the JSON or YAML form of docs/guide/paths.md (cdpr.path.parse),
or G-code (.gcode, .gc, .nc, .ngc: cdpr.path.gcode) starting at the robot's home, every
corner rounded by --blend (m, default 0: G-code corners are stopped at).  --margin:
the tensions kept this far (N) inside their range (default: workspace.margin).

Exit 0: timed and accepted; 1: the path cannot be timed (the place is named) or the
validation refuses the timing; 2: bad arguments, an unreadable file or config.
--json prints one object: poses, waypoints, duration_s, peak_linear_speed,
peak_angular_speed, seconds (to time it), accepted, refusal, saved.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path as FilePath
from typing import Any

import numpy as np

from cdpr import ConfigError
from cdpr.path import Path
from cdpr.trajectory import Trajectory, TrajectoryError
from daemon.cli.exit_codes import EXIT_FAILED, EXIT_OK, EXIT_USAGE
from daemon.cli.input_files import UsageError, read_path
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.run_cmd import report
from daemon.config import DaemonConfig, load_config
from daemon.service.planner import path_timer, validate_as_the_daemon


def add_parser(subparsers: Any) -> None:
    """Register `plan` on the cdprd subcommand parsers."""
    p = subparsers.add_parser(
        "plan", help="time a path (JSON/YAML poses or G-code) within the cables' tensions"
    )
    p.add_argument("file", help="a path (docs/guide/paths.md: JSON or YAML) or G-code")
    p.add_argument("--config", required=True, help="daemon config")
    p.add_argument("--blend", type=float, default=0.0, help="G-code: corner blend radius, m")
    p.add_argument("--margin", type=float, help="tension margin, N (default: workspace.margin)")
    p.add_argument("--output", help="save the timed trajectory here (JSON, for cdprd send)")
    add_json_flag(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
        path = read_path(args.file, config, args.blend)
        margin = config.workspace.margin if args.margin is None else args.margin
        if not (math.isfinite(margin) and margin >= 0.0):
            raise UsageError(f"--margin: {margin:g} must be a number >= 0")
    except ConfigError as exc:
        report(exc, args.json)
        return EXIT_USAGE
    except (UsageError, TrajectoryError) as exc:
        print_error("usage", str(exc), args.json)
        return EXIT_USAGE
    began = time.perf_counter()
    try:
        trajectory = path_timer(config, margin)(path)
    except TrajectoryError as exc:
        print_error("rejected", str(exc), args.json, prefix=f"cannot time {args.file}")
        return EXIT_FAILED
    seconds = time.perf_counter() - began
    refusal = _refusal(trajectory, config)
    saved = None
    if args.output and refusal is None:
        FilePath(args.output).write_text(json.dumps(trajectory.as_dict()))
        saved = args.output
    summary = _summary(path, trajectory, seconds, refusal, saved)
    print_result(summary, args.json, lambda: print(_text(args.file, summary)))
    return EXIT_OK if refusal is None else EXIT_FAILED


def _refusal(trajectory: Trajectory, config: DaemonConfig) -> str | None:
    """What the daemon's validation says of the timed trajectory, None if accepted."""
    try:
        validate_as_the_daemon(trajectory, config)
    except TrajectoryError as exc:
        return str(exc)
    return None


def _summary(
    path: Path, trajectory: Trajectory, seconds: float, refusal: str | None, saved: str | None
) -> dict[str, Any]:
    times = np.linspace(trajectory.start_time, trajectory.end_time, 2000)
    twists = np.array([trajectory.sample(float(t)).twist for t in times])
    return {
        "poses": len(path.points),
        "waypoints": len(trajectory),
        "duration_s": trajectory.duration,
        "peak_linear_speed": float(np.max(np.linalg.norm(twists[:, :3], axis=1))),
        "peak_angular_speed": float(np.max(np.linalg.norm(twists[:, 3:], axis=1))),
        "seconds": seconds,
        "accepted": refusal is None,
        "refusal": refusal,
        "saved": saved,
    }


def _text(file: str, s: dict[str, Any]) -> str:
    lines = [
        f"{file}: {s['poses']} poses, timed to {s['duration_s']:.3f} s in {s['seconds']:.2f} s "
        f"({s['waypoints']} waypoints); peak speed {s['peak_linear_speed']:.3f} m/s, "
        f"{s['peak_angular_speed']:.3f} rad/s",
        "validation: accepted" if s["accepted"] else f"validation: refused: {s['refusal']}",
    ]
    if s["saved"]:
        lines.append(f"saved to {s['saved']} (fly it: cdprd send {s['saved']})")
    return "\n".join(lines)
