"""`cdprd workspace`: where the robot can go (tuning.workspace_map), summarised, drawn and
saved for the daemon.

    cdprd workspace --config FILE [--step M] [--tilt RAD] [--payload-max KG] [--margin N]
                    [--[no-]interference] [--output MAP] [--png FILE] [--mcap FILE] [--json]

FILE is a daemon config (its workspace box, environment and `workspace:` section) or a
bare robot file (the anchors' box, no environment, the section's defaults).  The map goes
to --output, else the config's workspace.map, else STATE_DIR/ROBOT.workspace; a robot file
without --output saves none.  --png draws slices at home, --mcap writes a Foxglove scene
(the workspace's boundary at home coloured by margin, the environment, the box).

--json prints one object: the summary (volume_m3: where every orientation is possible,
volume_per_orientation_m3, fraction, worst_margin_n, best_margin_n, points,
orientations, reasons, seconds, points_per_second), settings, fingerprint, saved (path
or null).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from cdpr import ConfigError, Robot
from cdpr.body import Environment
from cdpr.description import load_yaml
from cdpr.workspace_map import WorkspaceMap
from daemon.cli.output import add_json_flag, print_error, print_result
from daemon.cli.run_cmd import report
from daemon.config import DaemonConfig, SafetyConfig, load_config, workspace_box
from daemon.config.workspace_config import WorkspaceConfig
from daemon.config.workspace_files import stored_map


def add_parser(subparsers: Any) -> None:
    """Register `workspace` on the cdprd subcommand parsers."""
    p = subparsers.add_parser(
        "workspace", help="where the robot can go: wrench-feasible, clear, without interference"
    )
    p.add_argument("--config", required=True, help="daemon config, or a robot YAML")
    p.add_argument("--step", type=float, help="grid spacing, m (default: workspace.step)")
    p.add_argument("--tilt", type=float, help="tilt of the 8 orientations beside home, rad")
    p.add_argument("--payload-max", type=float, help="payload range 0..KG at the CoM")
    p.add_argument("--margin", type=float, help="capacity margin a point needs, N")
    p.add_argument(
        "--interference",
        action=argparse.BooleanOptionalAction,
        help="refuse cables that touch or cross the body (default: workspace.interference)",
    )
    p.add_argument("--output", help="where to save the map (default: from the config)")
    p.add_argument("--png", help="draw slices at home into this PNG")
    p.add_argument("--mcap", help="write the boundary as a Foxglove scene into this MCAP")
    add_json_flag(p)


COARSE_STEP = 0.1  # m: the grid check-config computes when no fresh map is saved


def summary(config: DaemonConfig) -> tuple[dict[str, Any], str]:
    """check-config's figures of the workspace and its line: the saved map's volume at
    home and at every orientation (and its fraction of the box) and its worst margin,
    else those of a coarse grid computed now (and why the map was not used)."""
    from tuning.workspace_map import compute_map

    section = config.workspace
    rules = f"margin >= {section.margin:g} N at rest" + (
        ", cables' interference refused" if section.interference else ""
    )
    workspace, source = stored_map(config)
    if workspace is None:
        settings = section.map_settings(config.safety.tilt_max, max(section.step, COARSE_STEP))
        lower, upper = config.workspace_box
        workspace = compute_map(config.robot, lower, upper, config.environment, settings)
        grid = f"{settings.step * 100:g} cm"
        source = f"{source}; computed on a {grid} grid (`cdprd workspace` saves the map)"
    found = workspace.summary()
    home = found["volume_per_orientation_m3"][0]
    every, fraction = found["volume_m3"], found["fraction"]
    worst = found["worst_margin_n"]
    margin = "none inside" if worst is None else f"worst margin {worst:.1f} N"
    volumes = f"{home:.3g} m^3 at home, {every:.3g} m^3 ({fraction:.0%} of the box) at every tilt"
    figures = {
        "margin_n": section.margin,
        "interference": section.interference,
        "volume_at_home_m3": home,
        "volume_m3": every,
        "fraction": fraction,
        "worst_margin_n": worst,
        "source": source,
    }
    return figures, f"workspace: {rules}; {volumes}, {margin} ({source})"


def coarse_map(path: str, step: float = COARSE_STEP) -> WorkspaceMap:
    """The workspace of a daemon config or robot file (as `cdprd workspace` reads it) on a
    `step` grid: for `cdprd analyze --plot`."""
    from tuning.workspace_map import compute_map

    robot, _, lower, upper, environment, section, tilt_max = _load(path)
    settings = section.map_settings(tilt_max, step)
    return compute_map(robot, lower, upper, environment, settings)


def run(args: argparse.Namespace) -> int:
    from tuning.workspace_map import compute_map

    try:
        robot, config, lower, upper, environment, section, tilt_max = _load(args.config)
        settings = section.map_settings(
            tilt_max,
            step=_checked(args.step, "--step", positive=True),
            tilt=_checked(args.tilt, "--tilt"),
            payload_max=_checked(args.payload_max, "--payload-max"),
            margin=_checked(args.margin, "--margin"),
            interference=args.interference,
        )
    except ConfigError as exc:
        report(exc, args.json)
        return 1
    workspace = compute_map(robot, lower, upper, environment, settings)
    summary = workspace.summary()
    target = _map_path(args.output, config)
    try:
        saved = _save(workspace, target)
    except OSError as exc:
        print_error("not_written", f"cannot save the workspace map to {target}: {exc}", args.json)
        return 1
    if args.png:
        from tuning.workspace_map import plot_slices

        plot_slices(workspace, args.png, f"{robot.name}: capacity margin at home")
    if args.mcap:
        _write_mcap(workspace, robot, args.mcap, lower, upper, environment)
    out = {
        **summary,
        "settings": vars(settings),
        "fingerprint": workspace.fingerprint,
        "saved": saved,
    }
    print_result(
        out,
        args.json,
        lambda: print(describe(robot.name, workspace.quaternions, summary, settings, saved)),
    )
    return 0


def describe(
    name: str, quaternions: np.ndarray, summary: dict[str, Any], settings: Any, saved: str | None
) -> str:
    """The summary as text, a line per orientation."""
    lines = [
        f"workspace of {name}: {settings.step * 100:g} cm grid, {len(quaternions)} orientations "
        f"(home and tilted {settings.tilt:g} rad), payload {settings.payload[0]:g}-"
        f"{settings.payload[1]:g} kg, capacity margin >= {settings.margin:g} N, "
        + ("cables' interference checked" if settings.interference else "interference not checked"),
    ]
    box = summary["points"] / summary["orientations"] * settings.step**3
    for q, volume in zip(quaternions, summary["volume_per_orientation_m3"], strict=True):
        angle = 2.0 * math.acos(min(1.0, abs(float(q[0]))))
        label = "home" if angle < 1e-9 else f"tilted about ({_axis(q)})"
        lines.append(f"  {label}: {volume:.3g} m^3 ({100 * volume / box:.0f} % of the box)")
    worst, best = summary["worst_margin_n"], summary["best_margin_n"]
    lines.append(
        f"  at every orientation: {summary['volume_m3']:.3g} m^3 "
        f"({100 * summary['fraction']:.0f} % of the box)"
        + ("" if worst is None else f"; margins {worst:.1f} to {best:.1f} N")
    )
    reasons = ", ".join(f"{name} {count}" for name, count in summary["reasons"].items())
    lines.append(f"  points: {reasons}")
    lines.append(
        f"computed in {summary['seconds']:.1f} s ({summary['points_per_second']} points/s)"
        + (f"; saved to {saved}" if saved else "; not saved (no --output, map or state_dir)")
    )
    return "\n".join(lines)


def _axis(q: np.ndarray) -> str:
    v = np.asarray(q[1:], dtype=float)
    v = v / np.linalg.norm(v)
    return ", ".join(f"{c:.2f}" for c in (np.round(v, 2) + 0.0).tolist())  # no -0.00


def _load(
    path: str,
) -> tuple[Robot, DaemonConfig | None, np.ndarray, np.ndarray, Environment, WorkspaceConfig, float]:
    """A daemon config's or a bare robot file's robot, config (None), workspace box,
    environment, `workspace:` section and safety.tilt_max."""
    data = load_yaml(path)
    if isinstance(data, dict) and "drives" in data:
        config = load_config(path)
        lower, upper = config.workspace_box
        workspace = config.workspace
        return (
            config.robot,
            config,
            lower,
            upper,
            config.environment,
            workspace,
            config.safety.tilt_max,
        )
    robot = Robot.from_yaml(path)
    safety = SafetyConfig()
    lower, upper = workspace_box(robot, safety)
    return robot, None, lower, upper, Environment(), WorkspaceConfig(), safety.tilt_max


def _checked(given: float | None, flag: str, positive: bool = False) -> float | None:
    """A flag's value (None if not given), refused unless finite and > 0 (`positive`)
    or >= 0."""
    if given is None:
        return None
    if not math.isfinite(given) or given < 0.0 or (positive and given == 0.0):
        raise ConfigError(
            f"{flag}: {given:g} must be a {'positive number' if positive else 'number >= 0'}"
        )
    return given


def _map_path(output: str | None, config: DaemonConfig | None) -> Path | None:
    """Where the map goes: --output, else the config's (None: a robot file alone)."""
    return Path(output) if output else (config.workspace_map_path() if config else None)


def _save(workspace: WorkspaceMap, target: Path | None) -> str | None:
    """The map saved at `target` (its directory made), its path; None saves nothing."""
    if target is None:
        return None
    target.parent.mkdir(parents=True, exist_ok=True)
    workspace.save(target)
    return str(target)


def _write_mcap(
    workspace: Any,
    robot: Robot,
    path: str,
    lower: np.ndarray,
    upper: np.ndarray,
    environment: Environment,
) -> None:
    from foxglove.messages import SceneUpdate
    from mcap.writer import Writer

    from cdpr.workspace_map import shell
    from daemon.process.scene import SCENE_TOPIC, workspace_scene

    voxels, margins = shell(workspace, 0)
    anchors = robot.geometry.anchors
    scene = workspace_scene((lower, upper), voxels, margins, workspace.step, environment, anchors)
    schema = SceneUpdate.get_schema()
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="", library="cdprd workspace")
        schema_id = writer.register_schema(
            name=schema.name, encoding=schema.encoding, data=schema.data
        )
        channel = writer.register_channel(
            topic=SCENE_TOPIC, message_encoding="protobuf", schema_id=schema_id
        )
        writer.add_message(channel, log_time=0, data=scene.encode(), publish_time=0)
        writer.finish()
