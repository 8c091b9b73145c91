"""Where a control cycle's time goes: the real daemon.service.service.Service with the
simulator in a process of its own on socket-pair buses (the core as `cdprd run --sim`
runs it, without the companion; at 1 kHz bench/loop.py's two-bus config), enabled and
flying gotos back and forth, its parts timed per cycle.

    python bench/cycle_profile.py [--json] [--seconds 6] [--rate 500] [--protocol cia402]
                                  [--cprofile N]

The parts are timed by wrapping the objects' methods from here (time.perf_counter_ns;
no timing code in the service), summed per cycle (a cycle: from the tick that opens it
to the end of its run, so the controller's work done ahead and the decoding of its
feedback frames count in it) and summarised as median / p99 / mean in microseconds.
A part nested in another (FK in the controller step) is counted in both; each row
names its parent, and `<part> (rest)` is what a parent spent outside its timed
children.  The wrappers cost `wrapper_ns` each (measured) and the parents carry
`wrapped_calls_per_cycle` of them, a little inflated: `service.compute_p50_us` /
`p99_us` is the service's own compute time (CycleStats, what `cdprd demo` prints),
measured in a window before the wrappers go in.  `state_snapshot_us`: Service.state(),
which the companion host takes at zenoh.state_rate_hz on the core (in the slack, not
in a cycle, but on its CPU), and the cycle statistics' summary it takes afresh once a
second.  `core_us_per_cycle`: the core process's CPU time per cycle in the instrumented
window (the wrappers' cost in it), `simulator_us_per_cycle` the simulator process's;
`idle_core_us_per_cycle` the core's before the robot is enabled (drives up, no
controller: the SYNC, the feedback's decoding and checks, the keep-alive frames and the
event loop), the floor under any controller.

--cprofile N profiles the instrumented window instead with cProfile and prints its
top N functions by own time (no per-part table: cProfile's overhead distorts it).
Figures are for this machine (shared, 2 vCPU: compare medians of several runs).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import pstats
import shutil
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from loop import process_cpu_seconds, rate_config

from cdpr import Pose
from cdpr.trajectory.core import Curve
from daemon.cli.simulated import ProcessSimulator
from daemon.service.planner import LocalLink, Planner, load_checks
from daemon.service.safety import SafetyState
from daemon.service.service import Service

SETTLE = 0.5  # s enabled before measuring
IDLE_SECONDS = 3.0  # s the core's CPU is measured with the drives up and nothing enabled
AMPLITUDE = 0.15  # m: the gotos go this far either side of home in x (and half in z)

# (part, parent, where: the service -> (object or class, method name; an object None
# where the config has no such part)); parents before children
Where = Callable[[Service], tuple[Any, str]]
PARTS: list[tuple[str, str | None, Where]] = [
    ("cycle", None, lambda s: (s, "_run_cycle")),
    ("prepare", None, lambda s: (s.controller, "prepare")),
    ("prepare.linearise", "prepare", lambda s: (s.controller.robot, "linearise_at")),
    ("prepare.reference_terms", "prepare", lambda s: (s.controller, "_reference_terms")),
    (
        "prepare.model_terms",
        "prepare.reference_terms",
        lambda s: (s.controller.robot, "model_terms"),
    ),
    ("prepare.factor", "prepare.reference_terms", lambda s: (s.controller.tension, "factored")),
    ("prepare.stretch", "prepare", lambda s: (s.controller.stretch, "update")),
    ("prepare.observer", "prepare", lambda s: (s.controller.observer, "update")),
    ("prepare.payload", "prepare", lambda s: (s.controller.payload, "update")),
    ("prepare.reference", "prepare", lambda s: (Curve, "sample")),
    ("prepare.tension_rate", "prepare", lambda s: (s.controller._tension_rate, "add")),
    ("receive_decode", None, lambda s: (s.driver, "receive")),
    ("sync_encode", None, lambda s: (s.driver, "cycle_start")),
    ("cycle.take_feedback", "cycle", lambda s: (s, "_take_feedback")),
    ("cycle.offsets_read", "cycle", lambda s: (s.offsets, "read")),
    ("cycle.offsets_watch", "cycle", lambda s: (s.offsets, "watch")),
    ("cycle.trusted_check", "cycle", lambda s: (s.trust, "check")),
    ("cycle.trusted_track", "cycle", lambda s: (s.trust, "track")),
    ("cycle.second_answers", "cycle", lambda s: (s, "_second_answers")),
    ("cycle.safety_drives", "cycle", lambda s: (s.monitor, "check_drives")),
    ("cycle.safety_freshness", "cycle", lambda s: (s.monitor, "check_freshness")),
    ("cycle.safety_bus", "cycle", lambda s: (s.monitor, "check_bus")),
    ("cycle.control", "cycle", lambda s: (s, "_control")),
    ("control.step", "cycle.control", lambda s: (s.controller, "step")),
    ("step.measure", "control.step", lambda s: (s.controller, "_measure")),
    ("step.stretch_observe", "control.step", lambda s: (s.controller.stretch, "observe")),
    ("step.command", "control.step", lambda s: (s.controller, "_command")),
    ("step.payload_observe", "control.step", lambda s: (s.controller.payload, "observe")),
    ("control.safety_output", "cycle.control", lambda s: (s.monitor, "check_output")),
    ("control.encode", "cycle.control", lambda s: (s.driver, "commands")),
    ("control.send", "cycle.control", lambda s: (s, "send")),
    ("cycle.after_commands", "cycle", lambda s: (s, "_after_commands")),
    ("after.note_pose", "cycle.after_commands", lambda s: (s.trust, "note_pose")),
    ("trust_catch_up", None, lambda s: (s.trust, "catch_up")),
    ("cycle.gc_policy", "cycle", lambda s: (s.collector, "after_cycle")),
]
PARENT = {name: parent for name, parent, _ in PARTS}


class Spans:
    """Nanoseconds per part, summed over the current cycle, then kept per cycle."""

    def __init__(self) -> None:
        self.current: dict[str, int] = defaultdict(int)
        self.per_cycle: dict[str, list[int]] = defaultdict(list)
        self.calls = 0  # wrapped calls, all cycles
        self.cycles = 0

    def wrap(self, owner: Any, attribute: str, part: str) -> None:
        """Time `owner.attribute(...)` as `part` from now on: an instance attribute that
        shadows the method (the callers look it up per call), or on a class, its method
        for every instance."""
        method = getattr(owner, attribute)
        clock, current = time.perf_counter_ns, self.current

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = clock()
            try:
                return method(*args, **kwargs)
            finally:
                current[part] += clock() - start
                self.calls += 1

        setattr(owner, attribute, timed)
        if part == "cycle":  # the end of a cycle: its sums are kept

            def closing(*args: Any, **kwargs: Any) -> Any:
                try:
                    return timed(*args, **kwargs)
                finally:
                    self._close_cycle()

            setattr(owner, attribute, closing)

    def _close_cycle(self) -> None:
        self.cycles += 1
        for part in PARENT:
            self.per_cycle[part].append(self.current.get(part, 0))
        self.current.clear()

    def table(self) -> dict[str, dict[str, Any]]:
        """Per part: its parent, median / p99 / mean us per cycle and its mean over the
        slowest 1 % of cycles (`tail_us`: what the cycle's p99 is made of); and per parent
        with timed children, the rest it spent outside them."""
        out: dict[str, dict[str, Any]] = {}
        arrays = {part: np.array(values, dtype=float) for part, values in self.per_cycle.items()}
        cycle = arrays["cycle"]
        slowest = cycle >= np.percentile(cycle, 99)
        timed = [part for part in PARENT if part in arrays and arrays[part].any()]
        for part in timed:
            out[part] = {"parent": PARENT[part], **_summary(arrays[part], slowest)}
            children = [arrays[c] for c in timed if PARENT[c] == part]
            if children:
                rest = arrays[part] - np.sum(children, axis=0)
                out[f"{part} (rest)"] = {"parent": part, **_summary(rest, slowest)}
        return out


def _summary(ns: np.ndarray, slowest: np.ndarray | None = None) -> dict[str, float]:
    out = {
        "p50_us": round(float(np.median(ns)) / 1e3, 1),
        "p99_us": round(float(np.percentile(ns, 99)) / 1e3, 1),
        "mean_us": round(float(ns.mean()) / 1e3, 1),
    }
    if slowest is not None:
        out["tail_us"] = round(float(ns[slowest].mean()) / 1e3, 1)
    return out


def wrapper_ns() -> float:
    """What one wrapped call adds (median of 10^4 calls of a wrapped no-op, minus the
    bare call)."""

    class Target:
        def nothing(self) -> None:
            return None

    bare, wrapped = Target(), Target()
    spans = Spans()
    spans.wrap(wrapped, "nothing", "prepare")
    clock, costs = time.perf_counter_ns, []
    for target in (bare, wrapped):
        samples = []
        for _ in range(10_000):
            start = clock()
            target.nothing()
            samples.append(clock() - start)
        costs.append(float(np.median(samples)))
    return round(costs[1] - costs[0], 1)


def snapshot_us(service: Service, calls: int = 50) -> dict[str, dict[str, float]]:
    """Median and p99 of Service.state(), the snapshot the companion publishes at
    zenoh.state_rate_hz, in the cycle's slack but on the core's CPU (`state`: with the
    cycle statistics' summaries as kept for up to a second), and of those summaries
    taken afresh, as once a second (`cycle_summary`: the rings of the cycles since the
    measurement began, 10^4 samples each at most, where a long-running daemon's are)."""
    clock = time.perf_counter_ns
    out = {}
    for name, call in (("state", service.state), ("cycle_summary", service.stats.summary)):
        samples = []
        for _ in range(calls):
            start = clock()
            call()
            samples.append(clock() - start)
        out[name] = _summary(np.array(samples, dtype=float))
    return out


def profiled(profiler: cProfile.Profile, owner: Any, attribute: str) -> None:
    """Profile `owner.attribute(...)` calls from now on (the rest of the loop, the
    simulator and the planner, runs unprofiled: profiling it all slows the loop until
    the robot brakes)."""
    method = getattr(owner, attribute)

    def calls(*args: Any, **kwargs: Any) -> Any:
        return profiler.runcall(method, *args, **kwargs)

    setattr(owner, attribute, calls)


async def fly(service: Service, planner: Planner, seconds: float) -> int:
    """Gotos back and forth across home for `seconds`; how many were flown."""
    home = service.robot.home
    flown, end = 0, time.monotonic() + seconds
    while time.monotonic() < end and service.machine.moving:
        side = 1.0 if flown % 2 == 0 else -1.0
        offset = np.array([side * AMPLITUDE, 0.0, 0.5 * side * AMPLITUDE])
        await planner.command("goto", {"pose": Pose(home.position + offset, home.quaternion)})
        while service.machine.state is SafetyState.TRACKING and time.monotonic() < end:
            await asyncio.sleep(0.01)
        flown += 1
    return flown


def measure(protocol: str, rate_hz: float, seconds: float, top: int) -> dict[str, Any]:
    """Enable, settle, fly `seconds` plain (the service's own figures), then `seconds`
    with every part wrapped (or, with `top`, under cProfile)."""
    folder = Path(tempfile.mkdtemp(prefix="cdprd-profile-"))
    config, path = rate_config(protocol, rate_hz, folder)
    load_checks(config)  # the planner's compiled checks, loaded before the cycle runs
    sim = ProcessSimulator(config, path, truth=False)
    out: dict[str, Any] = {"rate_hz": rate_hz, "protocol": protocol}

    async def profile(service: Service) -> None:
        planner = Planner(config, LocalLink(service))
        await asyncio.sleep(SETTLE)
        cycles, core = service.stats.cycles, time.process_time()
        await asyncio.sleep(IDLE_SECONDS)  # the drives up, the robot not enabled
        idle, ran = time.process_time() - core, service.stats.cycles - cycles
        if ran == 0:
            raise SystemExit(f"no cycle ran in {IDLE_SECONDS} s with the drives up")
        out["idle_core_us_per_cycle"] = round(idle * 1e6 / ran, 1)
        await service.command("enable", {})
        fresh = type(service.stats)(rate_hz)  # allocated before the measurement
        await asyncio.sleep(SETTLE)
        service.stats = fresh
        flown = await fly(service, planner, seconds)
        compute, prepare = service.stats.compute.summary_us(), service.stats.prepare.summary_us()
        out["service"] = {
            "cycles": service.stats.cycles,
            "gotos": flown,
            "compute_p50_us": compute["p50_us"],
            "compute_p99_us": compute["p99_us"],
            "prepare_p50_us": prepare["p50_us"],
            "misses": service.stats.deadline_misses + service.stats.overruns,
        }
        if top:
            profiler = cProfile.Profile()
            for owner, attribute in (
                (service, "_run_cycle"),
                (service.controller, "prepare"),
                (service.driver, "receive"),
            ):
                profiled(profiler, owner, attribute)
            await fly(service, planner, seconds)
            out["cprofile"] = profiler
        else:
            spans = Spans()
            for part, _, where in PARTS:
                owner, attribute = where(service)
                if owner is not None:
                    spans.wrap(owner, attribute, part)
            assert sim.process is not None
            simulated, core = process_cpu_seconds(sim.process.pid), time.process_time()
            out["gotos_instrumented"] = await fly(service, planner, seconds)
            cycles = max(spans.cycles, 1)
            out["cycles_instrumented"] = spans.cycles
            out["wrapped_calls_per_cycle"] = round(spans.calls / cycles, 1)
            out["parts"] = spans.table()
            out["core_us_per_cycle"] = round((time.process_time() - core) * 1e6 / cycles, 1)
            simulated = process_cpu_seconds(sim.process.pid) - simulated
            out["simulator_us_per_cycle"] = round(simulated * 1e6 / cycles, 1)
        out["state_snapshot_us"] = snapshot_us(service)
        fault = service.machine.fault  # what braked the robot, if it did
        out["braked"] = int(fault is not None)
        out["fault"] = "" if fault is None else f"{fault.trigger.value}: {fault.message}"

    try:
        asyncio.run(sim.serve(companion=False, after_start=profile))
    finally:
        shutil.rmtree(folder)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--seconds", type=float, default=6.0, help="per window")
    parser.add_argument("--rate", type=float, default=500.0, help="controller.rate_hz")
    parser.add_argument("--protocol", choices=["cia402", "odrive"], default="cia402")
    parser.add_argument("--cprofile", type=int, default=0, metavar="N", help="top N by own time")
    args = parser.parse_args()
    out = measure(args.protocol, args.rate, args.seconds, args.cprofile)
    if args.cprofile:
        stats = pstats.Stats(out.pop("cprofile"))
        print(json.dumps(out))
        stats.sort_stats("tottime").print_stats(args.cprofile)
        return
    out["wrapper_ns"] = wrapper_ns()
    if args.json:
        print(json.dumps(out))
        return
    parts = out.pop("parts")
    print(json.dumps(out))
    columns = ("p50_us", "p99_us", "mean_us", "tail_us")
    print(f"{'part':34s}" + "".join(f"{c.replace('_', ' '):>9s}" for c in columns))
    for part, row in parts.items():
        depth = 0
        parent = row["parent"]
        while parent is not None:
            depth += 1
            parent = PARENT.get(parent)
        label = "  " * depth + part
        print(f"{label:34s}" + "".join(f"{row[c]:9.1f}" for c in columns))


if __name__ == "__main__":
    main()
