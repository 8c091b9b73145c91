"""What one big input costs the control loop of a holding robot.

The daemon runs as `cdprd run` runs it: this process is its real-time core (the cycle,
SCHED_FIFO where permitted), its companion process serves zenoh on a free
tcp/127.0.0.1 port; the robot enabled and holding.  Then, from a separate process:

- trajectory: a valid N-waypoint trajectory (a slow circle about home, 10 ms between
  waypoints, under the size limits) is sent as a query on <prefix>/trajectory, and the
  robot follows it for a second after the reply (N = 0: nothing is sent, the robot
  holds for 4 s: the host's own figures, for comparison);
- junk: N bytes of JSON that decodes and then fails the schema (a list of numbers where
  waypoints belong), as a query on <prefix>/trajectory;
- can-flood: N frames on CAN ids no drive uses, --rate frames a second (default 10^6,
  a burst; a 1 Mbit/s bus carries at most ~8,000 such frames a second).  With `--bus
  loop` (the simulator in this process on the loop bus) they appear in the daemon's
  receive queue of the loop bus as a kernel would put them there, at no cost to this
  process and unseen by the simulated drives; with `--bus socketcand` the simulator is
  its own process serving its bus in the socketcand protocol, the daemon reads it
  through python-can's socketcand client, and a third process sends the frames through
  the simulator's server (the whole path of the two-process set-up, whose parsing of
  every frame, in the simulator and in python-can's client, lies in front of the
  feedback).

Per run: the longest the loop was kept from its callbacks (`loop_gap_ms`, the largest
lateness of a 1 kHz timerfd callback, as in bench/flood.py), deadline misses and
overruns of the control cycle, and whether the robot braked (with the fault).  Printed
per size: every run and the median of the runs.

    python bench/stall.py trajectory [--sizes 1000 5000 10000] [--runs 3] [--json]
    python bench/stall.py junk [--sizes 2000000] [--runs 3] [--json]
    python bench/stall.py can-flood [--sizes 30000] [--bus loop|socketcand] [--rate HZ]

`--slow MS` turns on asyncio's debug mode and logs every loop callback that ran longer
than MS milliseconds, naming it (debug mode slows the loop: figures are then not
comparable).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
from flood import LagProbe, cycle_figures
from timing import free_endpoint, ordinary_child

from daemon.cli.simulated import InProcessSimulator
from daemon.config import DaemonConfig, load_config
from daemon.process.app import serve
from daemon.service.cycle_stats import CycleStats
from daemon.service.safety import SafetyState
from daemon.service.service import Service

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/stall"
HOME = (0.0, 0.0, 1.25)
SPACING = 0.01  # s between waypoints
RAMP = 1.0  # s over which a circle's pace eases in and out
FLOOD_IDS = range(0x6E0, 0x6F0)  # SDO requests to nodes 0x60-0x6F: no drive here uses them
DEFAULT_SIZES = {"trajectory": [1000, 5000, 10000], "junk": [2_000_000], "can-flood": [30000]}
AFTER = 1.0  # s measured after the input was answered (or sent)
QUIET = 3.0  # s of the quiet reference (size 0), about a 10,000-waypoint message's


def circle_trajectory(n: int) -> dict[str, Any]:
    """n waypoints SPACING apart: a 5 cm circle about home every 10 s with a slow yaw,
    beginning and ending at home at rest, its pace eased in and out over RAMP seconds
    (within the reference configs' jerk limit: a circle at full pace from the first
    waypoint asks 6,000 m/s^3 of the first 10 ms, and is refused)."""
    loops = max(1, round(n * SPACING / 10.0))
    t = SPACING * np.arange(n)
    ease = np.clip(np.minimum(t, t[-1] - t) / RAMP, 0.0, 1.0)
    pace = ease**3 * (10.0 - 15.0 * ease + 6.0 * ease**2)  # smootherstep: 0 to 1 and back
    travelled = np.concatenate([[0.0], np.cumsum(0.5 * (pace[1:] + pace[:-1]))])
    angles = 2.0 * math.pi * loops * travelled / travelled[-1]
    waypoints = []
    for k, angle in enumerate(angles.tolist()):
        yaw = 0.05 * math.sin(angle)
        waypoints.append(
            {
                "t": k * SPACING,
                "position": [
                    HOME[0] + 0.05 * math.sin(angle),
                    HOME[1] + 0.05 * (1.0 - math.cos(angle)),
                    HOME[2],
                ],
                "quaternion": {"w": math.cos(yaw / 2), "x": 0.0, "y": 0.0, "z": math.sin(yaw / 2)},
            }
        )
    return {"version": 1, "id": f"circle-{n}", "waypoints": waypoints}


# -- the other processes ----------------------------------------------------------------------


def send_trajectory(endpoint: str, n: int) -> dict[str, Any]:
    """(Child) the n-waypoint circle as a query, once the daemon answers; its reply."""
    return query_trajectory(endpoint, json.dumps(circle_trajectory(n)).encode())


def junk(n: int) -> bytes:
    """n bytes of JSON that decodes and then fails the schema: a list of numbers where
    waypoints belong (the interface decodes it whole before it can refuse it)."""
    head, tail = b'{"waypoints": [', b"0]}"
    return head + b"0.123456789, " * ((n - len(head) - len(tail)) // 13) + tail


def query_trajectory(endpoint: str, payload: bytes) -> dict[str, Any]:
    """(Child) `payload` as a query on <prefix>/trajectory, once the daemon answers; its
    size, the reply's verdict and how long it took."""
    import zenoh

    from daemon.config.zenoh_config import client_zenoh_config

    with zenoh.open(client_zenoh_config([endpoint])) as session:
        deadline = time.monotonic() + 10.0
        while not list(session.get(f"{PREFIX}/cmd/status", timeout=1.0)):
            if time.monotonic() > deadline:
                raise SystemExit("the daemon does not answer")
        began = time.monotonic()
        replies = list(session.get(f"{PREFIX}/trajectory", payload=payload, timeout=120.0))
        took = time.monotonic() - began
    sample = replies[0].ok if replies[0].ok is not None else replies[0].err
    body = json.loads(sample.payload.to_bytes())
    verdict = "accepted" if body.get("ok") else body["error"]["code"]
    if not body.get("ok"):
        verdict += ": " + body["error"].get("reason", "")[:200]
    return {"bytes": len(payload), "reply": verdict, "reply_s": round(took, 2)}


def flood_frames(n: int) -> list[can.Message]:
    return [
        can.Message(
            arbitration_id=FLOOD_IDS[k % len(FLOOD_IDS)],
            data=k.to_bytes(4, "little") + bytes(4),
            is_extended_id=False,
        )
        for k in range(n)
    ]


def send_flood(port: int, channel: str, n: int, rate: float) -> dict[str, Any]:
    """(Child) n frames through a socketcand client of the simulator's server, at most
    `rate` a second."""
    frames = flood_frames(n)
    bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
    try:
        began = time.monotonic()
        for k, frame in enumerate(frames):
            ahead = k / rate - (time.monotonic() - began)
            if ahead > 1e-3:
                time.sleep(ahead)
            bus.send(frame)
        took = time.monotonic() - began
    finally:
        bus.shutdown()
    return {"frames": n, "send_s": round(took, 3)}


# -- the daemon (this process) ----------------------------------------------------------------


def daemon_config(endpoint: str, bus: dict[str, Any] | None = None) -> DaemonConfig:
    """The example config on `endpoint`; on another bus (socketcand) feedback may be
    stale for as long as the drives' watchdog allows (50 ms = 25 cycles), since the
    example's 3 cycles brake at start-up over socketcand."""

    def edit(data: dict) -> None:
        data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
        data["zenoh"].update(listen=[endpoint], prefix=PREFIX)
        if bus is not None:
            data["can"] = bus
            data["safety"]["stale_cycles"] = 25

    return load_config(CONFIG, edit)


async def hold_and_measure(
    config: DaemonConfig, bus: can.BusABC, disturb: Callable[[], Any], sim: Any = None
) -> dict[str, Any]:
    """Run the daemon on `bus` as `cdprd run` does (this process the real-time core, its
    companion process serving zenoh), enable and hold, then `await disturb()` (returns
    what it learnt) and measure the core until AFTER seconds past its end."""
    out: dict[str, Any] = {}

    async def measure(service: Service) -> None:
        probe = LagProbe(asyncio.get_running_loop())
        try:
            await service.command("enable", {})
            await asyncio.sleep(1.0)
            out["setup_gap_ms"] = round(probe.figures()["max_us"] / 1e3, 2)
            if service.machine.state is not SafetyState.HOLD:
                out["braked_before"] = True
                out["fault"] = _fault(service)
                return
            service.stats = CycleStats(config.controller.rate_hz)
            out["input"] = await disturb()
            await asyncio.sleep(AFTER)
            figures = cycle_figures(service.stats)
            lag = probe.figures()
        finally:
            probe.close()
        out.update(
            loop_gap_ms=round(lag["max_us"] / 1e3, 2),
            deadline_misses=service.stats.deadline_misses,
            overruns=service.stats.overruns,
            cycles=figures["cycles"],
            deadline_misses_per_1e4=figures["deadline_misses_per_1e4"],
            overruns_per_1e4=figures["overruns_per_1e4"],
            braked=service.machine.state is SafetyState.BRAKED,
            state=service.machine.state.value,
            fault=_fault(service),
            frames=service.state()["frames"],
        )

    try:
        await serve(config, bus, after_start=measure)
    finally:
        if sim is not None:
            sim.close()
    return out


def _fault(service: Service) -> str | None:
    fault = service.machine.fault
    return None if fault is None else fault.line()


async def child(*args: str) -> dict[str, Any]:
    return await ordinary_child(__file__, *args)


async def trajectory_run(n: int, what: str = "trajectory") -> dict[str, Any]:
    """n waypoints (or, `what` junk, n bytes of junk); 0: nothing sent for QUIET seconds
    (the host's own misses and gaps)."""
    endpoint = free_endpoint()
    config = daemon_config(endpoint)
    sim = InProcessSimulator(config)
    sim.start()

    async def disturb() -> dict[str, Any]:
        if n == 0:
            await asyncio.sleep(QUIET)
            return {"sent": None}
        return await child(f"--send-{what}", endpoint, str(n))

    return await hold_and_measure(config, sim.daemon_bus, disturb, sim)


async def flood_run_socketcand(n: int, rate: float) -> dict[str, Any]:
    endpoint = free_endpoint()
    serve = ["--serve-socketcand", "127.0.0.1:0", "--duration", "120"]
    simulator = subprocess.Popen(
        [sys.executable, "-m", "sim_bus", "--config", str(CONFIG), *serve],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = simulator.stdout.readline()
        match = re.search(r"serving socketcand on 127\.0\.0\.1:(\d+) channel (\S+)", line)
        if not match:
            raise SystemExit(f"the simulator did not start: {line!r}")
        port, channel = int(match[1]), match[2]
        can_section = {
            "interface": "socketcand",
            "channel": channel,
            "options": {"host": "127.0.0.1", "port": port},
        }
        config = daemon_config(endpoint, can_section)
        bus = config.buses[0].open()
        try:
            return await hold_and_measure(
                config, bus, lambda: child("--send-flood", str(port), channel, str(n), str(rate))
            )
        finally:
            bus.shutdown()
    finally:
        simulator.terminate()
        simulator.wait(10)


async def flood_run_loop(n: int, rate: float) -> dict[str, Any]:
    """The flood appears in the daemon's receive queue of the loop bus at `rate` frames a
    second, as a kernel would put it there: at no cost to this process, and unseen by
    the simulated drives (a drive's acceptance filter drops such frames in hardware)."""
    endpoint = free_endpoint()
    config = daemon_config(endpoint)
    sim = InProcessSimulator(config)
    sim.start()
    frames = flood_frames(n)
    rx = sim.daemon_bus._rx  # the queue LoopBus.send fills, and its eventfd

    async def disturb() -> dict[str, Any]:
        began, sent = time.monotonic(), 0
        while sent < n:
            due = min(n, max(sent + 1, round((time.monotonic() - began) * rate)))
            with rx.lock:
                if not rx.queue:
                    os.eventfd_write(rx.fd, 1)
                rx.dropped += max(0, len(rx.queue) + due - sent - rx.queue.maxlen)
                rx.queue.extend(frames[sent:due])  # a full queue drops its oldest
            sent = due
            await asyncio.sleep(1e-3)
        return {"frames": n, "send_s": round(time.monotonic() - began, 3), "lost": rx.dropped}

    return await hold_and_measure(config, sim.daemon_bus, disturb, sim)


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of each figure over the runs, and how many braked."""
    done = [r for r in runs if "loop_gap_ms" in r]
    out: dict[str, Any] = {"runs": len(runs), "braked": sum(bool(r.get("braked")) for r in done)}
    keys = ("loop_gap_ms", "deadline_misses", "overruns", "cycles")
    for key in (*keys, "deadline_misses_per_1e4", "overruns_per_1e4"):
        if done:
            out[f"median_{key}"] = statistics.median(r[key] for r in done)
    out["braked_before_input"] = sum(bool(r.get("braked_before")) for r in runs)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", nargs="?", choices=["trajectory", "junk", "can-flood"])
    parser.add_argument("--sizes", type=int, nargs="+", help="waypoints or frames")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--bus", choices=["loop", "socketcand"], default="loop")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--slow", type=float, metavar="MS", help="log callbacks over MS ms")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--send-trajectory", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--send-junk", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--rate", type=float, default=1e6, help="flood: frames a second")
    parser.add_argument("--send-flood", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.send_trajectory:
        endpoint, n = args.send_trajectory
        print(json.dumps(send_trajectory(endpoint, int(n))))
        return
    if args.send_junk:
        endpoint, n = args.send_junk
        print(json.dumps(query_trajectory(endpoint, junk(int(n)))))
        return
    if args.send_flood:
        port, channel, n, rate = args.send_flood
        print(json.dumps(send_flood(int(port), channel, int(n), float(rate))))
        return
    if args.case is None:
        parser.error("name a case: trajectory, junk or can-flood")
    if args.one is not None:  # one run, in this process
        print(json.dumps(asyncio.run(one_run(args, args.one))))
        return
    out = {}
    for n in args.sizes or DEFAULT_SIZES[args.case]:
        runs = [fresh_run(args, n) for _ in range(args.runs)]
        out[str(n)] = {"summary": summarise(runs), "each": runs}
        if not args.json:
            print(n, json.dumps(out[str(n)], indent=1), flush=True)
    if args.json:
        print(json.dumps(out))


def fresh_run(args: argparse.Namespace, n: int) -> dict[str, Any]:
    """One run in a process of its own (no garbage or threads left by the one before)."""
    command = [sys.executable, __file__, args.case, "--bus", args.bus, "--one", str(n)]
    command += ["--rate", str(args.rate)]
    if args.slow is not None:
        command += ["--slow", str(args.slow)]
    done = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(done.stdout)


async def one_run(args: argparse.Namespace, n: int) -> dict[str, Any]:
    if args.slow is not None:
        logging.basicConfig(level=logging.WARNING)
        loop = asyncio.get_running_loop()
        loop.set_debug(True)
        loop.slow_callback_duration = args.slow / 1e3
    if args.case in ("trajectory", "junk"):
        return await trajectory_run(n, args.case)
    if args.bus == "socketcand":
        return await flood_run_socketcand(n, args.rate)
    return await flood_run_loop(n, args.rate)


if __name__ == "__main__":
    main()
