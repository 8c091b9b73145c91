"""`python -m sim_bus --config FILE`: the simulator as its own process.

It answers as the config's drives on the bus the config names (the in-process loop bus,
socketcan such as vcan0, or a socketcand server), optionally serves its bus to other
processes in the socketcand protocol (`--serve-socketcand 127.0.0.1:PORT`), injects
device and frame faults on a schedule (or device faults typed on standard input with
`--fault-input`, one `KIND:CABLE` per line), and prints the bus load every few seconds.
`--truth-log FILE` writes the platform's TRUE pose (the plant's, not what the drives
report) as one JSON line every TRUTH_PERIOD s, flushed at once, for tests and
experiments that must see what really moved: {"t": simulated s, "monotonic": that instant
on this host's monotonic clock (s), "position": [x, y, z], "quaternion": {"w", "x", "y",
"z"}, "lowest_tension": N, "tensions": [N, ...], "latest_wake_up_ms": how late its latest
wake-up since the last line came (sim_bus.runner.HELD_UP or more: the host did not run
this process), "slowest_answer_ms": the longest a SYNC waited for its answers to leave
since then, "late_answers": how many SYNCs were answered after --answer-deadline since
then (SimulatorRunner.take_answers)}.  `--bus-fd` runs it on inherited socket pairs
(sim_bus.bus.pairbus) instead of the config's buses: `cdprd demo`'s simulator.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import signal
import socket
import sys
from collections.abc import Callable
from typing import TextIO

import can

from cdpr import ConfigError
from drivers.gc_policy import CollectorPolicy
from sim_bus.bus.busload import BusLoadMeter
from sim_bus.bus.frame_faults import FaultyBus, parse_frame_faults
from sim_bus.bus.pairbus import PairBus
from sim_bus.bus.socketcand import SocketcandServer
from sim_bus.config import SimSetup, load_sim_setup
from sim_bus.runner import SimulatorRunner
from sim_bus.virtual_robot import VirtualRobot

log = logging.getLogger("sim_bus")

DEVICE_FAULTS = ("silent", "stuck", "glitch", "drive", "snap")
CLEAR = "clear"  # --fault-input's CLEAR:CABLE ends the cable's silent, stuck and glitch
GLITCH = 0.1  # m a glitching drive's reported length jumps by
TRUTH_PERIOD = 0.02  # s between two lines of --truth-log


def parse_device_fault(
    text: str, when: bool = True, kinds: tuple[str, ...] = DEVICE_FAULTS
) -> tuple[str, int, float]:
    """KIND:CABLE@T, e.g. snap:3@2.5 (cable 3 snaps at t = 2.5 s); with `when` False,
    KIND:CABLE (now) and t is 0; KIND one of `kinds`."""
    form = "KIND:CABLE@SECONDS" if when else "KIND:CABLE"
    try:
        kind, rest = text.split(":", 1)
        cable, at = rest.split("@", 1) if when else (rest, "0")
        parsed = (kind, int(cable), float(at))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"fault {text!r}: expected {form}, KIND one of {', '.join(kinds)}"
        ) from None
    if parsed[0] not in kinds:
        raise argparse.ArgumentTypeError(
            f"fault kind {parsed[0]!r} unknown; use one of {', '.join(kinds)}"
        )
    return parsed


def parse_address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    try:
        return host or "127.0.0.1", int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT") from None


def fault_action(robot: VirtualRobot, kind: str, cable: int) -> Callable[[], list[can.Message]]:
    """The device fault `kind` on `cable` (or CLEAR: its faults ended), as an action
    for SimulatorRunner.at."""
    if not 0 <= cable < robot.n:
        raise ConfigError(f"fault on cable {cable}: the robot has cables 0..{robot.n - 1}")

    def act() -> list[can.Message]:
        if kind == CLEAR:  # the drive reconnected, its encoder repaired
            log.warning("clearing the faults of cable %d at t=%.3f s", cable, robot.t)
            robot.silence(cable, False)
            robot.stick_encoder(cable, False)
            robot.glitch_encoder(cable, 0.0)
            return []
        log.warning("injecting %s fault on cable %d at t=%.3f s", kind, cable, robot.t)
        if kind == "silent":
            robot.silence(cable)
        elif kind == "stuck":
            robot.stick_encoder(cable)
        elif kind == "glitch":
            robot.glitch_encoder(cable, GLITCH)
        elif kind == "snap":
            robot.snap_cable(cable)
        else:
            return robot.drive_fault(cable, text="injected overcurrent")
        return []

    return act


def _seconds(text: str) -> float:
    """A duration in seconds: finite and not negative (argparse's error otherwise)."""
    value = float(text)
    if not 0.0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a duration >= 0 s")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m sim_bus", description=__doc__)
    parser.add_argument(
        "--config", required=True, help="daemon config YAML (robot, drives, can, sim)"
    )
    parser.add_argument("--serve-socketcand", type=parse_address, metavar="HOST:PORT")
    parser.add_argument(
        "--bus-fd",
        type=int,
        action="append",
        default=[],
        metavar="FD",
        help="an inherited end of a socket pair (sim_bus.bus.pairbus) as the bus, in place "
        "of the config's: one per bus of the config's can section, in its order",
    )
    parser.add_argument(
        "--fault",
        type=parse_device_fault,
        action="append",
        default=[],
        help="device fault KIND:CABLE@SECONDS, KIND in silent, stuck, glitch (the reported "
        f"length jumps {GLITCH} m), drive, snap (repeatable)",
    )
    parser.add_argument(
        "--fault-input",
        action="store_true",
        help="also read faults from standard input, one KIND:CABLE per line, injected at "
        f"once ({CLEAR}:CABLE ends the cable's silent, stuck and glitch faults)",
    )
    parser.add_argument("--drop", type=float, default=0.0, help="drop this fraction of frames")
    parser.add_argument(
        "--corrupt", type=float, default=0.0, help="corrupt this fraction of frames"
    )
    parser.add_argument("--delay", type=float, default=0.0, help="delay every frame by SECONDS")
    parser.add_argument(
        "--error-burst",
        type=float,
        default=0.0,
        metavar="PERIOD",
        help="an error frame every PERIOD seconds",
    )
    parser.add_argument(
        "--truth-log",
        metavar="FILE",
        type=argparse.FileType("w", encoding="utf-8"),
        help=f"write the platform's true pose as JSON lines every {TRUTH_PERIOD} s",
    )
    parser.add_argument(
        "--answer-deadline",
        type=_seconds,
        default=0.0,
        metavar="SECONDS",
        help="count SYNCs answered more than SECONDS after they went out (the host's "
        "feedback deadline) in the truth log's late_answers (0: not counted)",
    )
    parser.add_argument("--duration", type=float, default=0.0, help="stop after SECONDS (0: run)")
    parser.add_argument("--report-every", type=float, default=5.0, help="bus-load report period")
    return parser


def frame_fault_flags(args: argparse.Namespace) -> dict:
    """The command-line frame faults as a frame_faults config section."""
    section: dict = {}
    if args.drop:
        section["drop"] = [{"name": "cli-drop", "probability": args.drop}]
    if args.corrupt:
        section["corrupt"] = [{"name": "cli-corrupt", "probability": args.corrupt}]
    if args.delay:
        section["delay"] = [{"name": "cli-delay", "delay": args.delay, "probability": 1.0}]
    if args.error_burst:
        section["error_bursts"] = [{"name": "cli-errors", "period": args.error_burst}]
    return section


async def simulate(setup: SimSetup, args: argparse.Namespace) -> int:
    flags = frame_fault_flags(args)
    faults = parse_frame_faults(flags, "command line") if flags else setup.sim.frame_faults
    # on pair buses (the daemon's own simulator) the config's server is not started
    configured = None if args.bus_fd else _address(setup.sim.serve_socketcand)
    address = args.serve_socketcand or configured
    if address is not None and len(setup.buses) > 1:
        raise ConfigError(
            "--serve-socketcand / sim.serve_socketcand serves one bus; can: lists "
            f"{len(setup.buses)}"
        )
    if args.bus_fd and (address is not None or len(args.bus_fd) != len(setup.buses)):
        raise ConfigError(
            f"--bus-fd: {len(args.bus_fd)} given for the config's {len(setup.buses)} buses"
            + (", and a pair bus is not served over socketcand" if address is not None else "")
        )
    device: dict[str, can.BusABC] = {}
    try:
        for k, c in enumerate(setup.buses):
            bus = pair_end(args.bus_fd[k], c.channel) if args.bus_fd else c.open()
            device[c.bus_name] = FaultyBus(bus, faults) if faults.named_rules() else bus
    except BaseException:
        for bus in device.values():
            bus.shutdown()
        raise
    robot = VirtualRobot(setup.robot, setup.drives, setup.sim.plant, setup.sim.rig)
    meters = {c.bus_name: BusLoadMeter(c.bitrate) for c in setup.buses}
    wake = setup.sim.wake(setup.drives)
    runner = SimulatorRunner(
        robot,
        device,
        meters,
        wake,
        collector=CollectorPolicy(),
        own_process=True,
        answer_deadline=args.answer_deadline,
    )
    for kind, cable, at in args.fault:
        runner.at(at, fault_action(robot, kind, cable))
    server = None
    served_bus = None
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    runner.start()
    try:
        if address is not None:
            c = setup.buses[0]
            served_bus = c.open()  # the server's own reader of the same bus
            server = SocketcandServer(served_bus, address[0], address[1], channel=c.channel)
            await server.start()
            print(
                f"serving socketcand on {address[0]}:{server.port} channel {c.channel}", flush=True
            )
        on = ", ".join(f"{c.interface}:{c.channel}" for c in setup.buses)
        print(
            f"simulating {setup.robot.name}: {robot.n} {setup.drives.protocol} drives on {on}",
            flush=True,
        )
        if args.fault_input:
            fault_input = FaultInput(robot, runner, sys.stdin.fileno())
            loop.add_reader(sys.stdin.fileno(), fault_input.on_readable)
        if args.truth_log:
            truth = asyncio.create_task(log_truth(runner, args.truth_log, stop))
        if args.duration:
            loop.call_later(args.duration, stop.set)
        while not stop.is_set():
            try:
                await asyncio.wait_for(stop.wait(), args.report_every)
            except TimeoutError:
                for c in setup.buses:
                    report = meters[c.bus_name].report()
                    print(
                        f"t={runner.t:.1f} s bus load {report.load:.1%} "
                        f"({report.window_frames} frames/s at {c.bitrate} bit/s)"
                        + (f" on bus {c.bus_name}" if len(setup.buses) > 1 else "")
                        + failure_note(runner),
                        flush=True,
                    )
        if args.truth_log:
            await truth
        return 0
    finally:
        runner.close()
        if server is not None:
            await server.stop()
        if served_bus is not None:
            served_bus.shutdown()
        for bus in device.values():
            bus.shutdown()


async def log_truth(runner: SimulatorRunner, out: TextIO, stop: asyncio.Event) -> None:
    """--truth-log: the plant's pose every TRUTH_PERIOD s until `stop`."""
    plant = runner.robot.plant
    with out:
        while not stop.is_set():
            pose = plant.pose
            w, x, y, z = pose.quaternion.tolist()
            tensions = plant.tensions
            slowest_answer, late_answers = runner.take_answers()
            line = {
                "t": plant.time,
                "monotonic": runner.monotonic(plant.time),
                "position": pose.position.tolist(),
                "quaternion": {"w": w, "x": x, "y": y, "z": z},
                "lowest_tension": float(tensions.min()),
                "tensions": tensions.tolist(),
                "latest_wake_up_ms": runner.take_latest_wake_up() * 1e3,
                "slowest_answer_ms": slowest_answer * 1e3,
                "late_answers": late_answers,
            }
            out.write(json.dumps(line) + "\n")
            out.flush()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), TRUTH_PERIOD)


class FaultInput:
    """--fault-input: KIND:CABLE lines on a file descriptor (stdin), each injected at
    once; a bad line is answered on stderr and changes nothing."""

    def __init__(self, robot: VirtualRobot, runner: SimulatorRunner, fd: int) -> None:
        self._robot, self._runner, self._fd = robot, runner, fd
        self._pending = b""

    def on_readable(self) -> None:
        chunk = os.read(self._fd, 4096)
        if not chunk:  # end of input: nothing more will come
            asyncio.get_running_loop().remove_reader(self._fd)
            return
        *lines, self._pending = (self._pending + chunk).split(b"\n")
        for raw in lines:
            line = raw.decode(errors="replace").strip()
            if line:
                self._inject(line)

    def _inject(self, line: str) -> None:
        try:
            kind, cable, _ = parse_device_fault(line, when=False, kinds=(*DEVICE_FAULTS, CLEAR))
            self._runner.at(self._runner.t, fault_action(self._robot, kind, cable))
        except (argparse.ArgumentTypeError, ConfigError) as exc:
            print(f"error: {exc}", file=sys.stderr, flush=True)


def pair_end(fd: int, channel: str) -> PairBus:
    """--bus-fd: the inherited socket `fd` as the bus `channel` (ConfigError if it is none)."""
    try:
        sock = socket.socket(fileno=fd)
    except OSError as exc:
        raise ConfigError(f"--bus-fd {fd}: not an open socket ({exc.strerror})") from None
    if sock.type != socket.SOCK_STREAM:
        sock.detach()
        raise ConfigError(f"--bus-fd {fd}: not a stream socket pair's end")
    return PairBus(sock, channel)


def _address(text: str | None) -> tuple[str, int] | None:
    return None if text is None else parse_address(text)


def failure_note(runner: SimulatorRunner) -> str:
    """The sends and receives that failed so far, where any did: a frame the drives
    never answered, or an answer never sent, shows here (not on the host)."""
    failed = [
        f"{count} {what} failed"
        for count, what in ((runner.send_errors, "sends"), (runner.receive_errors, "receives"))
        if count
    ]
    return f"; {', '.join(failed)}" if failed else ""


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        setup = load_sim_setup(args.config)
        return asyncio.run(simulate(setup, args))
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
