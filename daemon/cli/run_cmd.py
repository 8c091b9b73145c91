"""`cdprd run` (the service) and `cdprd sim` (the simulator as its own process)."""

from __future__ import annotations

import argparse
import asyncio
import sys

from cdpr import ConfigError
from daemon.config import DaemonConfig, load_config
from daemon.process.app import close_bus, open_bus, serve
from daemon.process.logsetup import configure_logging
from drivers.config import check_fall_on_axis_error


def add_parsers(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser(
        "run",
        help="run the daemon (hardware per the config's can section, or --sim)",
        description="Run the cdprd service.  It starts IDLE with every cable held; "
        "planners enable it and send trajectories over zenoh.",
    )
    run.add_argument("--config", required=True, help="daemon config YAML")
    run.add_argument(
        "--sim", action="store_true", help="drive an in-process simulator instead of hardware"
    )
    run.add_argument("--log-level", help="override logging.level (debug, info, warning, error)")
    run.set_defaults(handler=run_command)
    sim = sub.add_parser(
        "sim",
        help="run the simulator as its own process on the config's bus",
        description="Same as `python -m sim_bus`; see its --help for fault flags.",
        add_help=False,
    )
    sim.add_argument("rest", nargs=argparse.REMAINDER)
    sim.set_defaults(handler=sim_command)


def report(exc: ConfigError) -> None:
    """Print a config problem on stderr, each line as `error: FILE: KEY: problem`."""
    for line in str(exc).splitlines():
        print(f"error: {line}", file=sys.stderr)


def load_checked(path: str) -> DaemonConfig:
    """The daemon config at `path` with every section checked, `sim:` included: the
    service never reads it, but `check-config` and `run` refuse the same files."""
    from daemon.cli.simulated import sim_section  # sim_bus, for this check only (DESIGN §2)

    config = load_config(path)
    check_fall_on_axis_error(config.drives, config.source)
    sim_section(config)
    return config


def load_or_exit(path: str) -> DaemonConfig:
    try:
        return load_checked(path)
    except ConfigError as exc:
        report(exc)
        raise SystemExit(1) from None


def run_command(args: argparse.Namespace) -> int:
    config = load_or_exit(args.config)
    try:
        configure_logging(args.log_level or config.logging.level)
    except ConfigError as exc:
        report(exc)
        return 2
    try:
        return asyncio.run(_run(config, args.sim))
    except ConfigError as exc:  # the simulator of `run --sim` cannot be built
        report(exc)
        return 1


async def _run(config: DaemonConfig, sim: bool) -> int:
    if not sim:
        bus = open_bus(config)
        try:
            return await serve(config, bus)
        finally:
            close_bus(bus)
    from daemon.cli.simulated import InProcessSimulator

    return await InProcessSimulator(config).serve()


def sim_command(args: argparse.Namespace) -> int:
    from sim_bus.__main__ import main as sim_main

    return sim_main(args.rest)
