"""The `cdprd` command line."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

import numpy as np

from cdpr import ConfigError, Robot
from cdpr.description import load_yaml
from daemon.cli import (
    analyze_cmd,
    calibrate_cmd,
    client_cmd,
    completion,
    demo_cmd,
    plan_cmd,
    run_cmd,
    tune_cmd,
    workspace_cmd,
)
from daemon.cli.exit_codes import EXIT_FAILED, EXIT_OK, codes_of, epilog
from daemon.cli.output import CommandParser, add_json_flag, print_result
from daemon.config import check_workspace
from daemon.config.watchdog_drift import FORMULA
from daemon.config.zenoh_config import answers, taken
from drivers.cia402.profile import plans as drive_plans
from sim_bus.bus.cycle_frames import SIMULATED_BUS, bus_cycles

if TYPE_CHECKING:
    from daemon.cli.gain_check import GainCheck
    from daemon.config import DaemonConfig


def check_config(path: str, as_json: bool = False) -> int:
    """Validate a daemon config (or a bare robot description) and print a readable
    summary (`as_json`: one object, a key per line of it); 0 if it is sound, 1 with each
    problem named (`error: FILE: KEY: problem`) if not.  A daemon config passes only if
    `run` would take it (its gains stable: gain_check) and the simulator of `run --sim`
    can be built from it."""
    try:
        data = load_yaml(path)
        if isinstance(data, dict) and "drives" in data:
            from daemon.cli.simulated import sim_section, simulated_robot

            config, gains = run_cmd.load_for_run(path)
            simulated_robot(config, sim_section(config))
            check_workspace(config)
            robot = config.robot
        else:
            config, gains, robot = None, None, Robot.from_yaml(path)
    except ConfigError as exc:
        run_cmd.report(exc, as_json)
        return EXIT_FAILED
    summary, lines = config_summary(robot, config, gains)
    print_result(summary, as_json, lambda: print("\n".join(lines)))
    return EXIT_OK


def config_summary(
    robot: Robot, config: DaemonConfig | None, gains: GainCheck | None
) -> tuple[dict[str, Any], list[str]]:
    """check-config's summary of a robot (and of the daemon config around it): the
    figures by key, and the lines a person reads, each built beside its figures."""
    home = robot.home
    lengths = robot.cable_lengths(home)
    masses = robot.modal_masses(home)
    shown = ", ".join("inf" if np.isinf(m) else f"{m:.3g}" for m in masses)
    summary: dict[str, Any] = {
        "robot": {
            "name": robot.name,
            "cables": robot.n_cables,
            "platform_mass": robot.platform.mass,
            "home": {"position": home.position.tolist(), "quaternion": home.quaternion.tolist()},
            "cable_lengths_at_home": lengths.tolist(),
            "modal_masses_at_home": masses.tolist(),  # inf: null
        }
    }
    lines = [
        f"robot {robot.name}: {robot.n_cables} cables, platform {robot.platform.mass:g} kg",
        f"home position {np.round(home.position, 4).tolist()} m, "
        f"quaternion {np.round(home.quaternion, 6).tolist()}",
        f"cable lengths at home: {np.round(lengths, 4).tolist()} m",
        f"modal masses at home (Lemma 1, kg): {shown}",
    ]
    if config is None:
        return summary, lines
    d = config.drives
    drives: dict[str, Any] = {
        "protocol": d.protocol,
        "nodes": list(d.nodes),
        "brake": d.brake.value,
        "watchdog_timeout_s": d.watchdog_timeout,
    }
    summary["drives"] = drives
    lines.append(
        f"drives: {d.protocol} nodes {d.nodes}, brake {d.brake.value}, "
        f"watchdog {d.watchdog_timeout * 1e3:g} ms"
    )
    tolerance = config.feedback_tolerance
    summary["feedback_tolerance"] = {
        "total_m": tolerance.total, "quantisation_m": tolerance.quantisation,
        "noise_m": tolerance.noise, "stretch_m": tolerance.stretch,
        "configured": tolerance.configured is not None,
    }  # fmt: skip
    lines.append(tolerance.describe())
    loads: dict[str, float] = {}
    answered: dict[str, float] = {}  # s the feedback takes on each bus
    late: list[str] = []
    rate = config.controller.rate_hz
    if d.protocol == "cia402":  # what a dead daemon leaves behind (checked at load)
        plan = next(iter(drive_plans(d).values()))
        limit = config.safety.max_watchdog_drift
        drives.update(
            eds=str(plan.eds),
            drive_watchdog=plan.watchdog,
            host_heartbeat_period_s=d.host_heartbeat_period,
            host_node=d.profile.host_node,
            detection_s=plan.detection,
            drift={
                "formula": FORMULA,
                "limit_m": limit,
                "bounds": [
                    {"cable": b.cable, "node": b.node, "drift_m": b.drift}
                    for b in config.watchdog_drift
                ],
            },
        )
        lines += [
            f"drive profile: EDS {plan.eds}",
            f"drive watchdog (when the daemon dies): {plan.watchdog}",
            f"host heartbeat: every {d.host_heartbeat_period * 1e3:g} ms (node "
            f"{d.profile.host_node}); a drive notices a dead daemon within "
            f"{plan.detection * 1e3:g} ms",
            f"drift before a drive notices ({FORMULA}; limit {limit * 1e3:g} mm):",
            *(f"  {bound.text()}" for bound in config.watchdog_drift),
        ]
        cycles = bus_cycles(d, robot, config.buses)
        loads = {bus.name: bus.load(rate) for bus in cycles}
        answered = {bus.name: bus.feedback_time() for bus in cycles}
    deadline = config.safety.feedback_deadline / rate
    summary["buses"] = []
    for c in config.buses:
        nodes = list(d.nodes)
        if len(config.buses) > 1:
            nodes = [n for n, b in zip(d.nodes, d.bus_names(), strict=True) if b == c.bus_name]
        load, feedback = loads.get(c.bus_name), answered.get(c.bus_name)
        summary["buses"].append(
            {"name": c.bus_name, "interface": c.interface, "channel": c.channel,
             "bitrate": c.bitrate, "nodes": nodes, "load": load, "feedback_s": feedback}
        )  # fmt: skip
        where = f"bus: {c.interface} {c.channel} at {c.bitrate} bit/s"
        if len(config.buses) > 1:
            where = f"bus {c.bus_name}: {where.removeprefix('bus: ')}, nodes {nodes}"
        if load is not None:
            where += f", load {load * 100:.1f} % at {rate:g} Hz (worst-case stuffing)"
        lines.append(where)
        if feedback is not None:
            lines.append(
                f"  feedback on the bus {feedback * 1e6:.0f} us after each SYNC (the SYNC and "
                f"the drives' answers, worst-case stuffing), deadline {deadline * 1e6:.0f} us"
            )
            if feedback >= deadline and c.interface != SIMULATED_BUS:
                late.append(
                    f"safety.feedback_deadline: the SYNC and the drives' answers on bus "
                    f"{c.bus_name} take {feedback * 1e6:.0f} us of bus time (worst-case "
                    f"stuffing) and the deadline is {deadline * 1e6:.0f} us, before the "
                    "drives' own reaction: the feedback can be late every cycle, and the "
                    "daemon brakes on stale feedback; raise safety.feedback_deadline, lower "
                    "controller.rate_hz, or spread the drives over more buses"
                )
    summary["controller"] = {"rate_hz": rate, "model_at": config.controller.model_at}
    lines.append(
        f"controller: {rate:g} Hz, model at {config.controller.model_at}; home pose in W: yes"
    )
    if gains is not None:
        summary["gains"] = gains.figures()
        lines.append(gains.summary())
    summary["workspace"], line = workspace_cmd.summary(config)
    lines.append(line)
    prefix = config.zenoh.key_prefix(robot.name)
    listen = list(config.zenoh.listen_endpoints)
    summary["zenoh"] = {"prefix": prefix, "listen": listen}
    lines.append(f"zenoh: prefix {prefix}, listening on {', '.join(listen)}")
    warnings = late + [
        f"zenoh: {endpoint} is taken on this host now: `cdprd run` would stop with "
        "'Address already in use' (a zenoh router, rmw_zenohd too, takes 7447 by "
        "default): listen on a free port (zenoh.listen), or connect to the router "
        "(ros2.router, zenoh.connect)"
        for endpoint in filter(taken, listen)
    ]
    lines += warnings
    if config.ros2_router is not None:
        (router,) = config.ros2_router.connect
        up = answers(router)
        summary["ros2"] = {"node": config.ros2.node_name, "router": router, "router_answers": up}
        waits = "" if up else " (nothing listens there now: it joins when it does)"
        lines.append(
            f"ros2: node {config.ros2.node_name} on the ROS 2 graph's router {router}{waits}"
        )
    summary["warnings"] = warnings
    return summary, lines


def command_parser() -> argparse.ArgumentParser:
    """The `cdprd` command line, every subcommand (also the source of the CLI reference,
    daemon.cli.reference)."""
    parser = CommandParser(
        prog="cdprd", description="Hardware-interface daemon for cable-driven parallel robots."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check-config", help="validate a daemon config or robot file")
    check.add_argument("file", help="e.g. config/reference8-cia402.yaml or config/robots/*.yaml")
    add_json_flag(check, "print the summary as one JSON object (its warnings under warnings)")
    analyze_cmd.add_parser(sub)
    client_cmd.add_parsers(sub)
    run_cmd.add_parsers(sub)
    demo_cmd.add_parser(sub)
    tune_cmd.add_parser(sub)
    calibrate_cmd.add_parser(sub)
    workspace_cmd.add_parser(sub)
    plan_cmd.add_parser(sub)
    completion.add_parser(sub, parser)
    for name, command in completion.subcommands(parser).items():
        command.epilog = epilog(codes_of(name))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = command_parser()
    args = parser.parse_args(argv)
    if hasattr(args, "handler"):
        return args.handler(args)
    if hasattr(args, "run"):
        return args.run(args)
    if args.command == "analyze":
        return analyze_cmd.run(args)
    if args.command == "check-config":
        return check_config(args.file, args.json)
    if args.command == "workspace":
        return workspace_cmd.run(args)
    parser.error(f"unknown command {args.command}")
    return 2
