"""The `cdprd` command line."""

from __future__ import annotations

import argparse

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
from daemon.config import check_workspace
from daemon.config.watchdog_drift import FORMULA
from daemon.config.zenoh_config import answers, taken
from drivers.cia402.profile import plans as drive_plans
from sim_bus.bus.cycle_frames import bus_cycles


def check_config(path: str) -> int:
    """Validate a daemon config (or a bare robot description) and print a readable
    summary; 0 if it is sound, 1 with each problem named (`error: FILE: KEY: problem`)
    if not.  A daemon config passes only if `run` would take it (its gains stable:
    gain_check) and the simulator of `run --sim` can be built from it."""
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
        run_cmd.report(exc)
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
    if config is not None:
        d = config.drives
        print(
            f"drives: {d.protocol} nodes {d.nodes}, brake {d.brake.value}, "
            f"watchdog {d.watchdog_timeout * 1e3:g} ms"
        )
        loads: dict[str, str] = {}
        if d.protocol == "cia402":  # what a dead daemon leaves behind (checked at load)
            plan = next(iter(drive_plans(d).values()))
            print(f"drive profile: EDS {plan.eds}")
            print(f"drive watchdog (when the daemon dies): {plan.watchdog}")
            print(
                f"host heartbeat: every {d.host_heartbeat_period * 1e3:g} ms (node "
                f"{d.profile.host_node}); a drive notices a dead daemon within "
                f"{plan.detection * 1e3:g} ms"
            )
            limit = config.safety.max_watchdog_drift * 1e3
            print(f"drift before a drive notices ({FORMULA}; limit {limit:g} mm):")
            for bound in config.watchdog_drift:
                print(f"  {bound.text()}")
            rate = config.controller.rate_hz
            loads = {
                bus.name: f", load {bus.load(rate) * 100:.1f} % at {rate:g} Hz (worst-case "
                "stuffing)"
                for bus in bus_cycles(d, robot, config.buses)
            }
        for c in config.buses:
            where = f"bus: {c.interface} {c.channel} at {c.bitrate} bit/s"
            if len(config.buses) > 1:
                nodes = [n for n, b in zip(d.nodes, d.bus_names(), strict=True) if b == c.bus_name]
                where = f"bus {c.bus_name}: {where.removeprefix('bus: ')}, nodes {nodes}"
            print(where + loads.get(c.bus_name, ""))
        print(
            f"controller: {config.controller.rate_hz:g} Hz, model at {config.controller.model_at}; "
            f"home pose in W: yes"
        )
        if gains is not None:
            print(gains.summary())
        print(workspace_cmd.summary_line(config))
        prefix = config.zenoh.key_prefix(robot.name)
        listen = ", ".join(config.zenoh.listen_endpoints)
        print(f"zenoh: prefix {prefix}, listening on {listen}")
        for endpoint in filter(taken, config.zenoh.listen_endpoints):
            print(
                f"zenoh: {endpoint} is taken on this host now: `cdprd run` would stop with "
                "'Address already in use' (a zenoh router, rmw_zenohd too, takes 7447 by "
                "default): listen on a free port (zenoh.listen), or connect to the router "
                "(ros2.router, zenoh.connect)"
            )
        if config.ros2_router is not None:
            (router,) = config.ros2_router.connect
            waits = "" if answers(router) else " (nothing listens there now: it joins when it does)"
            print(f"ros2: node {config.ros2.node_name} on the ROS 2 graph's router {router}{waits}")
    return 0


def command_parser() -> argparse.ArgumentParser:
    """The `cdprd` command line, every subcommand (also the source of the CLI reference,
    daemon.cli.reference)."""
    parser = argparse.ArgumentParser(
        prog="cdprd", description="Hardware-interface daemon for cable-driven parallel robots."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check-config", help="validate a daemon config or robot file")
    check.add_argument("file", help="e.g. config/reference8-cia402.yaml or config/robots/*.yaml")
    analyze_cmd.add_parser(sub)
    client_cmd.add_parsers(sub)
    run_cmd.add_parsers(sub)
    demo_cmd.add_parser(sub)
    tune_cmd.add_parser(sub)
    calibrate_cmd.add_parser(sub)
    workspace_cmd.add_parser(sub)
    plan_cmd.add_parser(sub)
    completion.add_parser(sub, parser)
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
        return check_config(args.file)
    if args.command == "workspace":
        return workspace_cmd.run(args)
    parser.error(f"unknown command {args.command}")
    return 2
