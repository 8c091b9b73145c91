"""The daemon's control cycle against the in-process simulator: 8 drives on the loop
bus, enabled and holding, for a fixed time at 500 Hz and at 1000 Hz.

    python bench/loop.py --json [--seconds 10] [--protocol cia402|odrive]

Prints one JSON object keyed by rate: compute time of a cycle (controller + safety +
encode + send), the controller's work done ahead while the feedback is on its way
(prepare), latency from the last feedback frame of a cycle (or its tick, when streamed
ODrive feedback was complete before it) to the last command frame sent, deadline misses
+ overruns per 10^4 cycles, and the process's CPU share (daemon and simulator together:
they share the loop).  Figures are for this machine (2 vCPU); nothing here is hard real
time (PERF-FACTS).  `timer_floor_misses_per_1e4` is the host's share: overruns of a bare
timerfd loop that does nothing else, at the same rate for the same time (a vCPU not run
for a few ms misses periods whatever runs on it).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path

from daemon.cli.simulated import InProcessSimulator
from daemon.config import load_config
from daemon.service.service import Service
from drivers.clock import PeriodicTimer

CONFIGS = Path(__file__).resolve().parent.parent / "config"


async def measure(protocol: str, rate_hz: float, seconds: float) -> dict[str, float]:

    def at_rate(data: dict) -> None:
        data["controller"]["rate_hz"] = rate_hz
        data["drives"]["feedback_rate_hz"] = rate_hz

    config = load_config(CONFIGS / f"reference8-{protocol}.yaml", at_rate)
    sim = InProcessSimulator(config)
    sim.start()
    service = Service(config, sim.daemon_bus)
    try:
        await service.start()
        await service.command("enable", {})
        await asyncio.sleep(0.5)  # settle, then measure afresh
        service.stats = type(service.stats)(rate_hz)
        cpu0, wall0 = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu = (time.process_time() - cpu0) / (time.monotonic() - wall0)
        stats = service.stats
        if service.machine.fault is not None:
            raise SystemExit(f"braked during the benchmark: {service.machine.fault.line()}")
        compute, latency = stats.compute.summary_us(), stats.latency.summary_us()
        prepare = stats.prepare.summary_us()
        misses = stats.deadline_misses + stats.overruns
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
            "cpu_fraction": round(cpu, 3),
        }
    finally:
        service.close()
        sim.close()


async def timer_floor(rate_hz: float, seconds: float) -> float:
    """Overruns per 10^4 periods of a timerfd on an otherwise idle event loop."""
    loop = asyncio.get_running_loop()
    timer = PeriodicTimer(1.0 / rate_hz)
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--protocol", choices=["cia402", "odrive"], default="cia402")
    args = parser.parse_args()
    out = {}
    for rate in (500, 1000):
        figures = asyncio.run(measure(args.protocol, rate, args.seconds))
        figures["timer_floor_misses_per_1e4"] = asyncio.run(timer_floor(rate, args.seconds))
        out[str(rate)] = {k: float(v) for k, v in figures.items()}
        if not args.json:
            print(rate, out[str(rate)])
    if args.json:
        print(json.dumps(out))


if __name__ == "__main__":
    main()
