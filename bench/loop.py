"""The daemon's control cycle as `cdprd run --sim` runs it: the real-time core (this
process: SCHED_FIFO where permitted, memory locked), its companion process (zenoh) and
the simulator's 8 drives in a process of their own on socket-pair buses, enabled and
holding for a fixed time at 500 Hz and at 1000 Hz (`--rate` one of them); optionally
with a busy host.  At 1000 Hz the CiA 402 drives are on two buses with the compact PDO
layout (config/reference8-cia402-2bus.yaml): the default layout's frames need 267 % of one
1 Mbit/s bus at that rate (`cdprd check-config` prints it), which no robot can wire.

    python bench/loop.py --json [--seconds 10] [--protocol cia402|odrive] [--load N] [--flood]
                         [--view] [--rate 500|1000]

Per rate: compute time of a cycle (controller + safety + encode + send), the
controller's work done ahead while the feedback is on its way (prepare), latency from
the last feedback frame of a cycle (or its tick, when streamed ODrive feedback was
complete before it) to the last command frame sent, deadline misses + overruns per 10^4
cycles, and `braked` (1 if the robot braked during the measurement) with `fault`, its
trigger and message.  `core_cpu_fraction` is the core process's share of a CPU (what a
robot's computer pays for the cycle), `simulator_cpu_fraction` the simulator process's
(what real drives do in their own hardware).
`simulator_late_per_1e4`: the SYNCs the simulator's process answered after the feedback
deadline per 10^4 cycles (its truth log's late_answers), each a miss real drives would not
have caused: of `misses_per_1e4`, the simulator's share (CiA 402; ODrive feedback is
streamed, and counts none).
`timer_floor_misses_per_1e4` is the host's share, measured in the same conditions:
overruns of a bare timerfd loop at the same priority and load that does nothing else
(a vCPU not run for a few ms misses periods whatever runs on it).

--load N runs N CPU-bound processes at normal priority, --flood the mixed zenoh flood of
bench/flood.py (`--mix all`) against the companion, both for the whole measurement;
the figures without them are then printed beside, under "unloaded".  --view turns on the
interfaces that see the robot, at full rate on loopback: the live view (view: section at
its maximum 200 Hz) with a Foxglove client subscribed to every channel in a process of
its own (tests/foxglove_client.py; `view_messages` counts what it decoded), and ROS 2 over
rmw_zenoh (ros2: section at the loop rate) with a ROS 2 node subscribed to every topic of
its domain in another (tests/ros2_listener.py; `ros2_messages` counts what it decoded); the
figures without them, under the same load, under "no_view", and their ratios
(`view_latency_p99_ratio`, `view_misses_delta_per_1e4`).  Figures are for this machine
(2 vCPU); nothing here is hard real time (PERF-FACTS).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import yaml
from timing import free_endpoint

from daemon.cli.simulated import ProcessSimulator
from daemon.config import DaemonConfig, load_config
from daemon.process.realtime import Child, realtime, spawn_ordinary
from daemon.service.api import CommandError
from daemon.service.service import Service
from drivers.clock import PeriodicTimer

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "config"
SETTLE = 0.5  # s enabled before measuring
FLOOD_RATE = 2000.0  # puts per second
LOAD_START = 60.0  # s the flood may take to connect (its imports, on the busy host)
VIEW_RATE_HZ = 200.0  # the view: section's largest rate_hz
# the fastest cycle 8 CiA 402 drives of the default layout have on one 1 Mbit/s bus;
# faster, two buses with the compact layout, as a robot must be wired (check-config
# prints each bus's load)
ONE_BUS_HZ = 500.0
RATES = (500, 1000)  # Hz


def rate_config(
    protocol: str, rate_hz: float, folder: Path, view: bool = False
) -> tuple[DaemonConfig, Path]:
    """The example config at `rate_hz`, zenoh on a free loopback port (and, if `view`,
    the live view on another at its top rate and ROS 2 at the loop rate), written to a
    file in `folder` (the simulator's process reads it too) and loaded."""
    endpoint = free_endpoint()
    view_port = int(free_endpoint().rpartition(":")[2])
    source = CONFIGS / f"reference8-{protocol}.yaml"
    if protocol == "cia402" and rate_hz > ONE_BUS_HZ:
        source = CONFIGS / "reference8-cia402-2bus.yaml"
    data = yaml.safe_load(source.read_text())
    data["robot"] = str((source.parent / data["robot"]).resolve())
    data["controller"]["rate_hz"] = rate_hz
    data["drives"]["feedback_rate_hz"] = rate_hz
    data["zenoh"]["listen"] = [endpoint]
    data["logging"] = {"level": "warning"}
    if view:
        data["view"] = {"enabled": True, "port": view_port, "rate_hz": VIEW_RATE_HZ}
        data["ros2"] = {"enabled": True, "rate_hz": rate_hz}
    path = folder / f"loop-{protocol}-{rate_hz:g}.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_config(path), path


def process_cpu_seconds(pid: int) -> float:
    """CPU time (user + system) a process has used, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Load:
    """The busy host's processes (busy_host): `started` once the flood (if any) is on,
    `stop` kills them without waiting."""

    def __init__(self, children: list[Child], flood_out: int | None) -> None:
        self.children = children
        self._flood_out = flood_out  # the flooder's stdout: a line once it floods

    def started(self) -> bool:
        if self._flood_out is None:
            return True
        try:
            said = os.read(self._flood_out, 64)
        except BlockingIOError:
            return False
        os.close(self._flood_out)
        self._flood_out = None
        return bool(said)

    def stop(self) -> None:
        for child in self.children:
            child.kill()
        if self._flood_out is not None:
            os.close(self._flood_out)
            self._flood_out = None


@contextlib.contextmanager
def busy_host(
    config: DaemonConfig, load: int, flood: bool, seconds: float, viewed: list | None = None
) -> Iterator[Load]:
    """`load` CPU hogs and, with `flood`, bench/flood.py's mixed flood on the config's
    zenoh endpoint, at normal priority (spawned so even from the real-time core), for at
    most `seconds` (the flood from when it has connected: its imports take seconds on a
    busy host); stopped on exit, when they are also waited for.  With the config's view
    on, a Foxglove client too; the number of messages it decoded is appended to
    `viewed`."""
    env = dict(os.environ)
    hog = f"import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end: pass"
    children: list[Child] = [spawn_ordinary([sys.executable, "-c", hog], env) for _ in range(load)]
    flood_out = None
    if flood:
        endpoint = config.zenoh.listen_endpoints[0]
        prefix = config.zenoh.key_prefix(config.robot.name)
        argv = [sys.executable, str(ROOT / "bench" / "flood.py"), "--flooder", endpoint]
        argv += ["--prefix", prefix, "--seconds", str(seconds), "--rate", str(FLOOD_RATE)]
        argv += ["--mix", "all"]
        flood_out, flood_in = os.pipe()
        os.set_blocking(flood_out, False)
        children.append(spawn_ordinary(argv, env, stdout=flood_in))
        os.close(flood_in)
    viewers: list[tuple[Child, int]] = []  # each viewer and its stdout's read end
    if config.view.enabled:
        url = f"ws://{config.view.host}:{config.view.port}"
        watch = ["tests.foxglove_client", url, str(seconds)]
        port = config.zenoh.listen_endpoints[0].rpartition(":")[2]
        listen = ["tests.ros2_listener", port, str(config.ros2.domain_id), str(seconds)]
        for module in (watch, listen):
            read, write = os.pipe()
            argv = [sys.executable, "-m", *module]
            viewers.append(
                (spawn_ordinary(argv, {**env, "PYTHONPATH": str(ROOT)}, stdout=write), read)
            )
            os.close(write)
    busy = Load(children + [viewer for viewer, _ in viewers], flood_out)
    try:
        yield busy
    finally:
        busy.stop()
        for _viewer, read in viewers:
            with os.fdopen(read) as counted:
                lines = counted.read().split()
            if viewed is not None:
                viewed.append(int(lines[-1]) if lines else 0)
        for child in busy.children:
            while child.poll() is None:
                time.sleep(0.01)


def measure(
    protocol: str, rate_hz: float, seconds: float, load: int, flood: bool, view: bool = False
) -> dict:
    """One run of the daemon as `cdprd run --sim`: enable, settle, measure."""
    folder = Path(tempfile.mkdtemp(prefix="cdprd-loop-"))
    config, path = rate_config(protocol, rate_hz, folder, view)
    out: dict[str, float] = {}
    viewed: list[int] = []
    # the load is killed after the measurement and waited for once the daemon has
    # stopped: waiting in the daemon's loop would hold it up (the drives' heartbeat
    # consumers brake)
    with contextlib.ExitStack() as load_running:

        async def hold_and_measure(service: Service) -> None:
            try:
                await service.command("enable", {})
            except CommandError as exc:  # braked before it held: that is the figure
                out.update(braked=1, fault=f"enable refused: {exc.code}: {exc.reason}")
                return
            busy = load_running.enter_context(
                busy_host(config, load, flood, seconds + SETTLE + 5.0, viewed)
            )
            waited = time.monotonic() + LOAD_START
            while not busy.started():
                if time.monotonic() > waited:
                    raise SystemExit(f"the flood did not start within {LOAD_START:g} s")
                await asyncio.sleep(0.05)
            # made before the measurement: allocating its sample buffers (resident at
            # once in locked memory) holds the loop up for a few periods
            fresh = type(service.stats)(rate_hz)
            await asyncio.sleep(SETTLE)  # the robot settles, the load gets going
            service.stats = fresh
            assert sim.process is not None
            simulated0 = process_cpu_seconds(sim.process.pid)
            cpu0, wall0 = time.process_time(), time.monotonic()
            await asyncio.sleep(seconds)
            wall = time.monotonic() - wall0
            cpu = (time.process_time() - cpu0) / wall
            simulated = (process_cpu_seconds(sim.process.pid) - simulated0) / wall
            out.update(figures(service, rate_hz, cpu, simulated))
            late = late_answers(sim.truth, wall0, wall0 + wall)
            out["simulator_late_per_1e4"] = round(1e4 * late / max(service.stats.cycles, 1), 2)
            busy.stop()

        sim = ProcessSimulator(config, path)  # its truth log counts its late answers
        try:
            asyncio.run(sim.serve(after_start=hold_and_measure))
        finally:
            shutil.rmtree(folder)
    if view:
        out["view_messages"], out["ros2_messages"] = viewed if len(viewed) == 2 else (0, 0)
    return out


def late_answers(truth: list[dict], start: float, end: float) -> int:
    """The SYNCs the simulator answered after the feedback deadline between monotonic
    `start` and `end` (its truth log's lines, each counting those since the last)."""
    return sum(r["late_answers"] for r in truth if start < r["monotonic"] <= end)


def figures(service: Service, rate_hz: float, cpu: float, simulator: float) -> dict[str, float]:
    """The service's cycle figures; `cpu` the core process's share of a CPU, `simulator`
    the simulator process's."""
    stats = service.stats
    compute, latency = stats.compute.summary_us(), stats.latency.summary_us()
    prepare = stats.prepare.summary_us()
    misses = stats.deadline_misses + stats.overruns
    fault = service.machine.fault  # what braked the robot, if it did
    return {
        "rate_hz": rate_hz,
        "cycles": stats.cycles,
        "compute_p50_us": compute["p50_us"],
        "compute_p99_us": compute["p99_us"],
        "prepare_p50_us": prepare["p50_us"],
        "latency_p50_us": latency["p50_us"],
        "latency_p99_us": latency["p99_us"],
        "latency_max_us": latency["max_us"],
        "misses_per_1e4": round(1e4 * misses / max(stats.cycles, 1), 2),
        "core_cpu_fraction": round(cpu, 3),
        "simulator_cpu_fraction": round(simulator, 3),
        "braked": int(fault is not None),
        "fault": "" if fault is None else f"{fault.trigger.value}: {fault.message}",
    }


def timer_floor(config: DaemonConfig, seconds: float, load: int) -> float:
    """Overruns per 10^4 periods of a timerfd on an otherwise idle event loop, at the
    core's priority and under the same load."""

    async def count() -> float:
        loop = asyncio.get_running_loop()
        timer = PeriodicTimer(1.0 / config.controller.rate_hz)
        counts = [0, 0]  # periods, overruns

        def tick() -> None:
            expired = timer.expirations()
            counts[0] += expired
            counts[1] += max(expired - 1, 0)

        loop.add_reader(timer.fileno(), tick)
        try:
            await asyncio.sleep(seconds)
        finally:
            loop.remove_reader(timer.fileno())
            timer.close()
        return round(1e4 * counts[1] / max(counts[0], 1), 2)

    with realtime(config.realtime), busy_host(config, load, False, seconds + 5.0):
        return asyncio.run(count())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--protocol", choices=["cia402", "odrive"], default="cia402")
    parser.add_argument("--load", type=int, default=0, help="CPU-bound processes beside")
    parser.add_argument("--flood", action="store_true", help="bench/flood.py's mixed flood")
    parser.add_argument("--view", action="store_true", help="the live view, a client on it")
    parser.add_argument("--rate", type=int, action="append", choices=RATES,
                        help="one loop rate (Hz), again for more (default: both)")  # fmt: skip
    args = parser.parse_args()
    busy = args.load > 0 or args.flood
    out = {}
    for rate in args.rate or RATES:
        figures = measure(args.protocol, rate, args.seconds, args.load, args.flood, args.view)
        if args.view:
            plain = measure(args.protocol, rate, args.seconds, args.load, args.flood)
            figures["no_view"] = plain
            if "latency_p99_us" in figures and "latency_p99_us" in plain:  # both held
                figures["view_latency_p99_ratio"] = round(
                    figures["latency_p99_us"] / max(plain["latency_p99_us"], 1.0), 3
                )
                figures["view_misses_delta_per_1e4"] = round(
                    figures["misses_per_1e4"] - plain["misses_per_1e4"], 2
                )
        with tempfile.TemporaryDirectory() as folder:
            config, _ = rate_config(args.protocol, rate, Path(folder))
        figures["timer_floor_misses_per_1e4"] = timer_floor(config, args.seconds, args.load)
        if busy:
            figures["load"], figures["flood"] = args.load, int(args.flood)
            quiet = measure(args.protocol, rate, args.seconds, 0, False)
            quiet["timer_floor_misses_per_1e4"] = timer_floor(config, args.seconds, 0)
            figures["unloaded"] = quiet
        out[str(rate)] = figures
        if not args.json:
            print(rate, json.dumps(figures))
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
