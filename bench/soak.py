"""Long flights through the whole stack, counting the brakes and judging each one: the
simulator (`python -m sim_bus --fault-input`: the eight CiA 402 drives of
config/reference8-cia402.yaml behind its socketcand server) and `cdprd run` on that bus,
as processes at their real-time priorities, with --load CPU hogs beside them.

    python bench/soak.py --json [--minutes 5] [--load 2] [--seed 1] [--fault-every 45]

The daemon runs the shipped config, changed only where this bench must: its bus is the
simulator's socketcand server, zenoh listens on a free loopback port, and the cycle runs
at RATE_HZ, what the simulated 1 Mbit/s bus carries for eight drives (with the drives'
watchdog at WATCHDOG, as the start-up check of the drift a dead daemon allows requires).
A client flies random flights: a goto to a random pose within BOX of home, then a random
trajectory of a few waypoints from there at up to SPEED; one in HOLD_SHARE is held halfway.
About every --fault-every seconds (0: never) a device fault (FAULTS, on a random cable)
is typed into the simulator while a trajectory flies; after the brake that should
follow, the fault is cleared (`clear:CABLE`), the daemon reset and enabled again.

Every brake is counted by trigger and judged: one within CAUGHT_WITHIN s after an
injected fault is that fault caught (true); one after that but before a flight has ended
well again is the fault's aftermath (a stuck encoder under the drive's own hold leaves
its cable slack or overdrawn: the recovery, not the flight, is at fault), listed apart;
a drive's "heartbeat lost" where the daemon's record says it sent none for the drives'
consumer time (drivers.cia402.host) and a CPU of this machine was frozen for at least
HELD_UP_SHARE of that silence just before (tests.host_steal.FreezeWatch: a SCHED_FIFO 90
probe per CPU) is the machine holding the host up, the drive right to stop: listed apart
as `held_up`; any other is false, listed with its message.  A fault no brake followed
within CAUGHT_WITHIN is missed.  Printed (JSON with --json): seconds flown, flights,
holds, motions the daemon refused, brakes by trigger, `false_brakes` and the list,
`aftermath`, `held_up`, `injected`, `caught`, `missed`, the CPUs' freezes
(`cpu_freezes`: how many of at least FREEZE_REPORTED, the longest) and the daemon's most
frequent refusals.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from cdpr.robot import Robot  # noqa: E402
from daemon.interface.client import CdprClient, RequestError  # noqa: E402
from tests.host_steal import FreezeWatch  # noqa: E402
from tests.loopback import free_port  # noqa: E402
from tests.processes import (  # noqa: E402
    connect,
    finish,
    serve_simulator,
    socketcand_can,
    start_daemon,
    wait_status,
)

CONFIG = ROOT / "config" / "reference8-cia402.yaml"
ROBOT = ROOT / "config" / "robots" / "reference8.yaml"
RATE_HZ = 250  # eight drives' SYNC, TPDOs and RPDOs at 500 Hz load the 1 Mbit/s bus 133 %
# s: drives.watchdog_timeout, 5 ms under the shipped one: at RATE_HZ a dead daemon would
# otherwise go unnoticed long enough to drift more than the shipped max_watchdog_drift
WATCHDOG = 0.045
BOX = (0.25, 0.25, 0.15)  # m: motions stay within this of home on each axis
SPEED = 0.2  # m/s: the random trajectories' pace between waypoints
WAYPOINTS = (2, 5)  # a trajectory's waypoints after its start, at least and at most
HOLD_SHARE = 0.2  # of the flights: held halfway
# device faults a reset recovers from once the simulator ends them; not "silent": a drive
# silent for long may have lost power and its length offset, which takes homing
FAULTS = ("glitch", "stuck", "drive")
CAUGHT_WITHIN = 2.0  # s: a brake this soon after an injected fault is that fault caught
MOTION_TIMEOUT = 30.0  # s: the most one goto or trajectory may take to end
HELD_UP_SHARE = 0.5  # of the host's silence: a CPU freeze this long makes it the machine's
HELD_UP_WINDOW = 3.0  # s before the brake reached the client: where that freeze may lie
FREEZE_REPORTED = 0.02  # s: CPU freezes counted in the report


class Soak:
    """The client's side: flights, faults, and every brake with the time it came."""

    def __init__(self, client: CdprClient, faults_in: Any, home: list[float], rng: random.Random):
        self.client, self.faults_in, self.home, self.rng = client, faults_in, home, rng
        self.events: list[tuple[float, dict[str, Any]]] = []
        self.lock = threading.Lock()
        self.subscriber = client.subscribe_events(self._on_event)
        self.counts = {"flights": 0, "holds": 0, "refused": 0}
        self.injected: list[dict[str, Any]] = []
        self.refusals: Counter[str] = Counter()  # what the daemon said, how often
        self.settled = True  # no fault injected since the last flight that ended well

    def _on_event(self, event: dict[str, Any]) -> None:
        with self.lock:
            if event.get("event") == "brake":
                event = {**event, "settled": self.settled}
            self.events.append((time.monotonic(), event))

    def _wait(self, since: int, kinds: tuple[str, ...], timeout: float) -> dict[str, Any] | None:
        """The first event of `kinds` (or a brake) from event index `since` on."""
        end = time.monotonic() + timeout
        while True:
            with self.lock:
                for _, event in self.events[since:]:
                    if event.get("event") in (*kinds, "brake"):
                        return event
            if time.monotonic() >= end:
                return None
            time.sleep(0.02)

    def _mark(self) -> int:
        with self.lock:
            return len(self.events)

    def _target(self) -> list[float]:
        return [h + self.rng.uniform(-b, b) for h, b in zip(self.home, BOX, strict=True)]

    def fly(self, fault_due: bool) -> None:
        """One flight: a goto, then a trajectory from there (held halfway, or with a fault
        injected halfway when `fault_due`); a brake ends it and is recovered from."""
        if self.client.status()["state"] != "hold":  # braked, or a reset left it idle
            self._recover()
        start = self._target()
        mark = self._mark()
        if not self._request(lambda: self.client.goto(start)):
            time.sleep(0.5)  # out of reach, or busy: another target next time
            return
        ended = self._wait(mark, ("trajectory_done",), MOTION_TIMEOUT)
        if ended is None or ended.get("event") == "brake":
            self._recover()
            return
        points, t = [start], 0.0
        level = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
        waypoints = [{"t": 0.0, "position": start, "quaternion": level}]
        for _ in range(self.rng.randint(*WAYPOINTS)):
            point = self._target()
            t += max(math.dist(points[-1], point) / SPEED, 0.5)
            points.append(point)
            waypoints.append({"t": t, "position": point, "quaternion": level})
        mark = self._mark()
        if not self._request(lambda: self.client.send_trajectory({"waypoints": waypoints})):
            return
        self.counts["flights"] += 1
        held = not fault_due and self.rng.random() < HOLD_SHARE
        if held or fault_due:
            time.sleep(t / 2)
            if held:
                self.counts["holds"] += 1
                self._request(self.client.hold)
                ended = self._wait(mark, ("trajectory_done",), 0.0)  # a brake meanwhile?
                if ended is not None and ended.get("event") == "brake":
                    self._recover()
                time.sleep(0.5)
                return
            self._inject()
        ended = self._wait(mark, ("trajectory_done",), MOTION_TIMEOUT)
        if ended is None or ended.get("event") == "brake" or fault_due:
            self._recover()
        else:
            self.settled = True

    def _request(self, ask: Any) -> bool:
        try:
            ask()
        except RequestError as exc:
            self.counts["refused"] += 1
            self.refusals[str(exc)[:120]] += 1
            return False
        return True

    def _inject(self) -> None:
        kind, cable = self.rng.choice(FAULTS), self.rng.randrange(8)
        self.faults_in.write(f"{kind}:{cable}\n")
        self.faults_in.flush()
        self.injected.append({"at": time.monotonic(), "kind": kind, "cable": cable})
        self.settled = False

    def _recover(self) -> None:
        """The robot braked (or should have): every injected fault ended, reset, enable."""
        time.sleep(CAUGHT_WITHIN)  # a brake of the fault comes within this
        for cable in {f["cable"] for f in self.injected}:
            self.faults_in.write(f"clear:{cable}\n")
        self.faults_in.flush()
        time.sleep(0.5)
        if self.client.status()["state"] in ("braked", "idle"):
            self._request(self.client.reset)
            self._request(self.client.enable)

    def report(self, seconds: float, freezes: FreezeWatch) -> dict[str, Any]:
        """The figures of the module docstring, the brakes set beside the CPUs' freezes."""
        with self.lock:
            brakes = [(at, e) for at, e in self.events if e.get("event") == "brake"]
        by_trigger: dict[str, int] = {}
        false, aftermath, held_up, caught = [], [], [], set()
        for at, event in brakes:
            trigger = event["trigger"]
            by_trigger[trigger] = by_trigger.get(trigger, 0) + 1
            cause = next(
                (k for k, f in enumerate(self.injected) if 0.0 <= at - f["at"] <= CAUGHT_WITHIN),
                None,
            )
            brake = {"trigger": trigger, "message": event.get("message")}
            frozen = held_up_by(brake["message"] or "", at, freezes)
            if cause is not None:
                caught.add(cause)
            elif not event["settled"]:
                aftermath.append(brake)
            elif frozen is not None:
                held_up.append({**brake, "cpu_frozen_ms": round(frozen * 1e3, 1)})
            else:
                false.append(brake)
        missed = [
            {"kind": f["kind"], "cable": f["cable"]}
            for k, f in enumerate(self.injected)
            if k not in caught
        ]
        return {
            "seconds": round(seconds, 1),
            **self.counts,
            "brakes": by_trigger,
            "false_brakes": len(false),
            "false": false,
            "aftermath": aftermath,
            "held_up": held_up,
            "injected": len(self.injected),
            "caught": len(caught),
            "missed": missed,
            "cpu_freezes": {
                "count": sum(d >= FREEZE_REPORTED for _, _, d in freezes.freezes()),
                "longest_ms": round(freezes.longest(-math.inf, math.inf) * 1e3, 1),
            },
            "refusals": dict(self.refusals.most_common(5)),
        }


def held_up_by(message: str, at: float, freezes: FreezeWatch) -> float | None:
    """The CPU freeze (s) that held the host up, when `message` (a brake the client got at
    `at`) is a drive's lost heartbeat the daemon says it sent none of for the consumer time,
    and a CPU froze for HELD_UP_SHARE of that silence within HELD_UP_WINDOW before."""
    silence = re.search(r"sent no heartbeat for ([\d.]+) ms", message)
    if silence is None:
        return None
    longest = freezes.longest(at - HELD_UP_WINDOW, at)
    return longest if longest >= HELD_UP_SHARE * float(silence[1]) / 1e3 else None


def configs(tmp: Path, zenoh_port: int) -> tuple[Path, dict[str, Any]]:
    """The simulator's config file and the daemon's config data (module docstring)."""
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROBOT)
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{zenoh_port}"]
    data["controller"]["rate_hz"] = RATE_HZ
    data["drives"]["watchdog_timeout"] = WATCHDOG
    sim = tmp / "sim.yaml"
    sim.write_text(yaml.safe_dump(data))
    return sim, data


def soak(minutes: float, load: int, seed: int, fault_every: float, workdir: Path) -> dict:
    zenoh_port = free_port()
    sim_config, data = configs(workdir, zenoh_port)
    sim, port, channel = serve_simulator(sim_config, "--fault-input")
    data["can"] = socketcand_can(port, channel)
    daemon_config = workdir / "daemon.yaml"
    daemon_config.write_text(yaml.safe_dump(data))
    daemon = start_daemon(daemon_config, log=workdir / "daemon.log")
    hog = [sys.executable, "-c", "while True: pass"]
    hogs = [subprocess.Popen(hog) for _ in range(load)]
    try:
        with FreezeWatch() as freezes:
            client = connect(zenoh_port, daemon)
            wait_status(client, "idle", 30.0)
            client.enable()
            rng = random.Random(seed)
            runner = Soak(client, sim.stdin, list(Robot.from_yaml(ROBOT).home.position), rng)
            began = time.monotonic()
            next_fault = began + (rng.expovariate(1.0 / fault_every) if fault_every else math.inf)
            while time.monotonic() - began < 60.0 * minutes:
                due = time.monotonic() >= next_fault
                runner.fly(due)
                if due:
                    next_fault = time.monotonic() + rng.expovariate(1.0 / fault_every)
            report = runner.report(time.monotonic() - began, freezes)
        client.close()
    finally:
        for proc in hogs:
            proc.kill()
        finish(daemon)
        finish(sim)
    return {"minutes": minutes, "load": load, "seed": seed, "rate_hz": RATE_HZ, **report}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=5.0)
    parser.add_argument("--load", type=int, default=2, help="CPU-bound processes beside it")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--fault-every", type=float, default=45.0, help="s between faults (0: none)"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cdprd-soak-") as tmp:
        log = Path(tmp) / "daemon.log"
        try:
            result = soak(args.minutes, args.load, args.seed, args.fault_every, Path(tmp))
        except (AssertionError, RequestError) as exc:
            print(f"soak failed: {exc}", file=sys.stderr)
            print(*_tail(log), sep="\n", file=sys.stderr)
            return 1
        tail = _tail(log)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    if result["false_brakes"]:
        print(*tail, sep="\n", file=sys.stderr)
    return 0


def _tail(log: Path, lines: int = 30) -> list[str]:
    text = log.read_text() if log.exists() else ""
    return ["daemon log, last lines:", *text.splitlines()[-lines:]]


if __name__ == "__main__":
    sys.exit(main())
