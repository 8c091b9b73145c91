"""`cdprd run` (the service) and `cdprd sim` (the simulator as its own process)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Callable
from typing import Any

from cdpr import ConfigError
from daemon.config import DaemonConfig, load_config
from daemon.process.app import close_bus, open_bus, serve
from daemon.process.logsetup import configure_logging


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
    add_view_option(run)
    run.set_defaults(handler=run_command)
    sim = sub.add_parser(
        "sim",
        help="run the simulator as its own process on the config's bus",
        description="Same as `python -m sim_bus`; see its --help for fault flags.",
        add_help=False,
    )
    sim.add_argument("rest", nargs=argparse.REMAINDER)
    sim.set_defaults(handler=sim_command)


def add_view_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--view",
        nargs="?",
        const="",
        metavar="HOST:PORT",
        type=_view_address,
        help="serve the live 3-D view (Foxglove WebSocket) as the view: section says, "
        "on HOST:PORT or PORT if given (default 127.0.0.1:8765)",
    )


def _view_address(text: str) -> str:
    host, sep, port = text.rpartition(":")
    if text and not (port.isdigit() and (host or not sep)):
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT or PORT")
    return text


def view_edit(address: str | None) -> Callable[[dict[str, Any]], None] | None:
    """A config edit that turns the view on (at `address`, HOST:PORT or PORT, if not
    empty); None when the option was not given."""
    if address is None:
        return None

    def edit(data: dict[str, Any]) -> None:
        view = dict(data.get("view") or {}, enabled=True)
        if address:
            host, _, port = address.rpartition(":")
            view["port"] = int(port)
            if host:
                view["host"] = host.removeprefix("[").removesuffix("]")
        data["view"] = view

    return edit


def report(exc: ConfigError) -> None:
    """Print a config problem on stderr, each line as `error: FILE: KEY: problem`."""
    for line in str(exc).splitlines():
        print(f"error: {line}", file=sys.stderr)


def load_checked(path: str, edit: Callable[[dict], None] | None = None) -> DaemonConfig:
    """The daemon config at `path` (changed by `edit` first) with every section checked,
    `sim:` included: the service never reads it, but `check-config` and `run` refuse the
    same files."""
    from daemon.cli.simulated import sim_section  # sim_bus, for this check only (DESIGN §2)

    config = load_config(path, edit)
    sim_section(config)
    return config


def load_or_exit(path: str, edit: Callable[[dict], None] | None = None) -> DaemonConfig:
    try:
        return load_checked(path, edit)
    except ConfigError as exc:
        report(exc)
        raise SystemExit(1) from None


def run_command(args: argparse.Namespace) -> int:
    config = load_or_exit(args.config, view_edit(args.view))
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
