"""`cdprd run` (the service) and `cdprd sim` (the simulator as its own process)."""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cdpr import ConfigError
from daemon.cli.gain_check import GainCheck, stable_gains
from daemon.cli.output import print_error
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
        "--sim",
        action="store_true",
        help="drive the simulator (a process of its own) instead of hardware",
    )
    run.add_argument("--log-level", help="override logging.level (debug, info, warning, error)")
    add_interface_options(run)
    run.set_defaults(handler=run_command)
    sim = sub.add_parser(
        "sim",
        help="run the simulator as its own process on the config's bus",
        description="Same as `python -m sim_bus`; see its --help for fault flags.",
        add_help=False,
    )
    sim.add_argument("rest", nargs=argparse.REMAINDER)
    sim.set_defaults(handler=sim_command)


def add_interface_options(parser: argparse.ArgumentParser) -> None:
    """--view [HOST:PORT] and --record FILE.mcap, shared by `run` and `demo`."""
    parser.add_argument(
        "--view",
        nargs="?",
        const="",
        metavar="HOST:PORT",
        type=_view_address,
        help="serve the live 3-D view (Foxglove WebSocket) as the view: section says, "
        "on HOST:PORT or PORT if given (default 127.0.0.1:8765)",
    )
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record the run's telemetry to FILE.mcap with the run's start time inserted "
        "(recording.telemetry; Foxglove opens it)",
    )


def _view_address(text: str) -> str:
    host, sep, port = text.rpartition(":")
    if text and not (port.isdigit() and (host or not sep)):
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT or PORT")
    return text


def interface_edit(args: argparse.Namespace) -> Callable[[dict[str, Any]], None]:
    """The config edit of --view (the view on, at HOST:PORT or PORT if given) and
    --record (recording.telemetry, relative to the working directory)."""
    address, record = args.view, args.record

    def edit(data: dict[str, Any]) -> None:
        if address is not None:
            view = dict(data.get("view") or {}, enabled=True)
            if address:
                host, _, port = address.rpartition(":")
                view["port"] = int(port)
                if host:
                    view["host"] = host.removeprefix("[").removesuffix("]")
            data["view"] = view
        if record:
            recording = dict(data.get("recording") or {})
            recording["telemetry"] = str(Path(record).absolute())
            data["recording"] = recording

    return edit


def report(exc: ConfigError, as_json: bool = False) -> None:
    """Print a config problem on stderr, each line as `error: FILE: KEY: problem`; with
    `as_json` as an error object on stdout (code "invalid_config", each line in
    "problems")."""
    problems = str(exc).strip().splitlines()
    if as_json:
        reason = "; ".join(problems)
        print_error("invalid_config", reason, as_json, {"problems": problems})
        return
    for line in problems:
        print(f"error: {line}", file=sys.stderr)


def load_checked(path: str, edit: Callable[[dict], None] | None = None) -> DaemonConfig:
    """The daemon config at `path` (changed by `edit` first) with every section checked,
    `sim:` included: the service never reads it, but `check-config` and `run` refuse the
    same files."""
    from daemon.cli.simulated import sim_section  # sim_bus, for this check only (DESIGN §2)

    config = load_config(path, edit)
    check_fall_on_axis_error(config.drives, config.source)
    sim_section(config)
    return config


def load_for_run(
    path: str, edit: Callable[[dict], None] | None = None
) -> tuple[DaemonConfig, GainCheck]:
    """load_checked, and the controller's gains stable for the home modal masses at the
    configured rate (gain_check): what `run` and `check-config` refuse.  `tune` and
    `calibrate` take any gains (tune is how one finds stable ones)."""
    config = load_checked(path, edit)
    return config, stable_gains(config)


def load_or_exit(path: str, edit: Callable[[dict], None] | None = None) -> DaemonConfig:
    try:
        return load_for_run(path, edit)[0]
    except ConfigError as exc:
        report(exc)
        raise SystemExit(1) from None


def run_command(args: argparse.Namespace) -> int:
    _announce_cold_cache()
    config = load_or_exit(args.config, interface_edit(args))
    try:
        configure_logging(args.log_level or config.logging.level)
    except ConfigError as exc:
        report(exc)
        return 2
    try:
        return asyncio.run(_run(config, Path(args.config) if args.sim else None))
    except ConfigError as exc:  # the simulator of `run --sim` cannot be built
        report(exc)
        return 1
    except RuntimeError as exc:  # its process did not start
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _announce_cold_cache() -> None:
    """On a cold numba cache (the first start after an install or upgrade) the robot's
    kernels compile as its config loads (cdpr.robot.Robot._load_kernels: ~19 s on this
    2-vCPU host, longer on a small computer), before the companion can extend systemd's
    start timeout: the core extends it itself and says why in STATUS= (stderr stays the
    config's errors alone)."""
    from daemon.process import warm_up, wire
    from daemon.process.systemd import Notifier

    if warm_up.is_warm():
        return
    Notifier().notify(
        f"EXTEND_TIMEOUT_USEC={int(wire.STARTING_LIMIT * 1e6)}",
        "STATUS=numba's cache is not warmed up since the install or upgrade: the control "
        "cycle's kernels may compile now (once, up to minutes on a small computer)",
    )


async def _run(config: DaemonConfig, sim: Path | None) -> int:
    """Serve on the config's buses, or on a simulator of the config at `sim` in a
    process of its own (daemon.cli.simulated.ProcessSimulator: in the core's process,
    the core and the simulator needed most of a CPU at real-time priority, where the
    kernel's real-time throttling held both up for tens of milliseconds each second)."""
    if sim is None:
        bus = open_bus(config)
        try:
            return await serve(config, bus)
        finally:
            close_bus(bus)
    from daemon.cli.simulated import ProcessSimulator

    return await ProcessSimulator(config, sim, truth=False).serve()


def sim_command(args: argparse.Namespace) -> int:
    from sim_bus.__main__ import main as sim_main

    return sim_main(args.rest)
