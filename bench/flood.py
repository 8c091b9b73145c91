"""The control cycle of a running daemon, quiet and under a zenoh flood.

This process runs the daemon as `cdprd run --sim` does: it is the real-time core (the
cycle and the in-process simulator), and its companion process serves zenoh on a free
tcp/127.0.0.1 port; it enables the robot and has it follow one long slow trajectory, so
that it is TRACKING.  Then:

- quiet: the cycle figures for --seconds, nothing else on zenoh;
- flood: the same while a separate process (this script with --flooder) puts thousands
  of messages a second on <prefix>/trajectory (--mix, below) and sends a command or
  trajectory query every tenth put, counting the replies of each query.

Per phase: period jitter, compute time of a cycle, last feedback -> last command
latency (p50/p99/max, µs), deadline misses and overruns per 10^4 cycles, and the loop's
lag (how late a 1 kHz timer callback runs: p50/p99/max, share > 0.5 ms); the RSS of
the core and of the companion before and after the flood and their peaks; the frame
counters; and what the flooder sent and got back.  Mixes (what the puts are):

    parse    100-waypoint trajectories that parse but start in the past: the whole
             decoding cost, then a cheap refusal by the service
    valid    two-waypoint moves near home (accepted -> tracking, or busy)
    large    valid 100-waypoint trajectories (accepted: validated and blended in)
    hostile  malformed, non-unit, non-monotonic, deeply nested, oversized (refused
             unread) and ~2 MB messages (decoded, then refused)
    all      all of these, interleaved (40 % valid, 40 % hostile, 10 % parse, ...)
    refused  all but what the service would accept (parse and hostile), so that the
             robot keeps tracking its own trajectory: the interface's costs alone
    long     valid 10,000-waypoint trajectories (1.7 MB), each sent as a query: how long
             the daemon takes to accept one (parsed, validated, planned, acknowledged:
             "accepted_s") and what it costs the cycle meanwhile (--rate 0.05: one)

    python bench/flood.py [--json] [--seconds 5] [--rate 2000] [--mix refused] [--limit HZ]

--limit sets zenoh.ingress_limits_hz to HZ for `trajectory` and `cmd/*`: zenoh then
drops what comes faster before the daemon sees it (docs/reference/zenoh-api.md, "Flow control").

The default mix, "refused", measures the interface's own costs.  With "valid", "large"
or "all" the service also accepts trajectories while the robot moves: their validation
and approach planning run in the companion, the core only follows the planned curves.
Should the robot brake, the output says so ("state_after", "fault").
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import random
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from timing import free_endpoint, ordinary_child

from cdpr.trajectory import parse_trajectory
from daemon.cli.simulated import InProcessSimulator
from daemon.config import load_config
from daemon.service.cycle_stats import CycleStats
from daemon.service.planner import LocalLink, Planner, load_checks
from daemon.service.safety import SafetyState
from daemon.service.service import Service
from drivers.clock import PeriodicTimer

CONFIG = Path(__file__).resolve().parent.parent / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/flood"
HOME = (0.0, 0.0, 1.25)
MIXES = ("parse", "valid", "large", "hostile", "all", "refused", "long")
LONG_WAYPOINTS = 10_000  # the default max_waypoints
# radius (m), period (s) and waypoint spacing (s) of the circles the service accepts: they
# start at speed (3 mm/s), within the reference configs' jerk limit (50 m/s^3; 5 cm in
# 10 s needed 61 m/s^3 to leave rest in the first 0.1 s, and was refused)
GENTLE = (0.03, 60.0, 0.1)


# A query waits in the daemon's queue (16 deep, and undecoded ones weighing at most two of
# the largest: zenoh_io.QUEUED_LARGEST_MESSAGES) behind the trajectories before it: each
# parsed within the parse thread's CPU budget (a ~2 MB one can leave it seconds in debt)
# and validated in the control cycle's slack, so seconds under a flood; the client waits.
REPLY_TIMEOUT = 30.0  # s

# -- the messages ---------------------------------------------------------------------------


def circle(n: int, radius: float, period: float, dt: float) -> list[dict[str, Any]]:
    """n waypoints dt apart on a horizontal circle about HOME with a slow yaw."""
    out = []
    for k in range(n):
        angle = 2.0 * math.pi * k * dt / period
        yaw = 0.05 * math.sin(angle)
        out.append(
            {
                "t": k * dt,
                "position": [
                    HOME[0] + radius * math.sin(angle),
                    HOME[1] + radius * (1.0 - math.cos(angle)),
                    HOME[2],
                ],
                "quaternion": {"w": math.cos(yaw / 2), "x": 0.0, "y": 0.0, "z": math.sin(yaw / 2)},
            }
        )
    return out


def tracking_trajectory(seconds: float) -> dict[str, Any]:
    """A slow circle lasting `seconds` (the robot tracks it through both phases)."""
    n = max(3, int(seconds / 0.5) + 1)
    waypoints = circle(n, 0.03, 8.0, 0.5)
    waypoints[-1]["position"] = list(HOME)  # ends where it began, at rest
    waypoints[-1]["quaternion"] = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    return {"version": 1, "waypoints": waypoints}


def messages(mix: str, max_bytes: int) -> list[tuple[str, bytes]]:
    """(kind, payload) of one round of puts for `mix` (see the module's docstring)."""
    identity = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    near = [
        {"t": 0.0, "position": list(HOME), "quaternion": identity},
        {"t": 1.0, "position": [HOME[0] + 0.01, HOME[1], HOME[2]], "quaternion": identity},
    ]
    valid = {"version": 1, "waypoints": near}
    large = {"version": 1, "waypoints": circle(100, *GENTLE)}
    hostile = [
        b"not json",
        b'{"waypoints": [NaN]}',
        json.dumps({**valid, "waypoints": near[::-1]}).encode(),  # times decreasing
        json.dumps(
            {**valid, "waypoints": [near[0], {**near[1], "quaternion": {**identity, "z": 0.2}}]}
        ).encode(),
        json.dumps({**valid, "priority": "high"}).encode(),
        b'{"waypoints": [' + b"0, " * 5000 + b"0]}",
        b"[" * 50_000 + b"]" * 50_000,
    ]
    kinds = {
        "valid": [json.dumps(valid).encode()],
        "large": [json.dumps(large).encode()],
        "parse": [json.dumps({**large, "start": 1.0}).encode()],  # in the past: refused
        "hostile": hostile,
        "oversize": [b" " * (max_bytes + 1)],
        "big": [b'{"waypoints": [' + b"0.123456789, " * ((max_bytes - 64) // 13) + b"0]}"],
        "long": [json.dumps({"version": 1, "waypoints": circle(LONG_WAYPOINTS, *GENTLE)}).encode()],
    }
    counts = {
        "parse": {"parse": 1},
        "valid": {"valid": 1},
        "large": {"large": 1},
        "hostile": {"hostile": 14, "oversize": 1, "big": 1},
        "all": {"valid": 40, "parse": 10, "large": 2, "hostile": 40, "oversize": 1, "big": 1},
        "refused": {"parse": 40, "hostile": 60, "oversize": 1, "big": 1},
        "long": {"long": 1},
    }[mix]
    out = [
        (kind, kinds[kind][k % len(kinds[kind])]) for kind, n in counts.items() for k in range(n)
    ]
    random.Random(0).shuffle(out)
    return out


# -- the flooder (a separate process) ---------------------------------------------------------


def flooder(endpoint: str, prefix: str, seconds: float, rate: float, mix: str) -> dict[str, Any]:
    """Put at `rate` per second for `seconds`, a query every tenth put; the counts."""
    import zenoh

    from daemon.config.zenoh_config import client_zenoh_config

    round_ = messages(mix, 2 * 1024 * 1024)
    accepting = mix in ("valid", "large", "all", "long")  # else the service accepts nothing
    asked = next(p for k, p in messages("valid" if accepting else "parse", 1024))
    queries = [
        ("cmd/status", None),
        ("trajectory", asked),
        ("cmd/fly", None),
        ("cmd/goto", b'{"position": [0, 0, NaN]}'),
    ]
    replies: dict[int, list[str]] = {}
    asked_at: dict[int, float] = {}
    accepted_after: list[float] = []  # s from a trajectory query to its "ok"

    def on_reply(i: int, reply: zenoh.Reply) -> None:
        sample = reply.ok if reply.ok is not None else reply.err
        try:
            body = json.loads(sample.payload.to_bytes())
            code = "ok" if body.get("ok") else body["error"]["code"]
        except (ValueError, KeyError, TypeError):
            code = "not_json:" + sample.payload.to_bytes()[:40].decode(errors="replace")
        if code == "ok" and not replies[i] and i in asked_at:
            accepted_after.append(time.monotonic() - asked_at[i])
        replies[i].append(code)

    sent: Counter[str] = Counter()
    with zenoh.open(client_zenoh_config([endpoint])) as session:

        def ask(key: str, body: bytes | None) -> None:
            i = len(replies)
            replies[i] = []
            if key == "trajectory":
                asked_at[i] = time.monotonic()
            session.get(
                f"{prefix}/{key}", lambda r: on_reply(i, r), payload=body, timeout=REPLY_TIMEOUT
            )

        block = zenoh.CongestionControl.BLOCK  # every put reaches the daemon
        publisher = session.declare_publisher(f"{prefix}/trajectory", congestion_control=block)
        ask("cmd/status", None)  # connected once it is answered
        deadline = time.monotonic() + 10.0
        while not replies[0] and time.monotonic() < deadline:
            time.sleep(0.01)
        print("flooding", flush=True)  # for a parent that waits for the flood (loop.py)
        n = 0
        start = time.monotonic()
        while (now := time.monotonic() - start) < seconds:
            while n < now * rate and time.monotonic() - start < seconds:
                kind, payload = round_[n % len(round_)]
                if kind == "long":
                    ask("trajectory", payload)
                else:
                    publisher.put(payload)
                sent[kind] += 1
                n += 1
                if n % 10 == 0 and kind != "long":
                    ask(*queries[len(replies) % len(queries)])
            time.sleep(0.001)
        elapsed = time.monotonic() - start
        deadline = time.monotonic() + REPLY_TIMEOUT + 2.0
        while time.monotonic() < deadline and any(not r for r in replies.values()):
            time.sleep(0.05)
    codes = Counter(code for r in replies.values() for code in r)
    return {
        "puts": n,
        "puts_per_s": round(n / elapsed, 1),
        "bytes_per_s": round(sum(len(round_[i % len(round_)][1]) for i in range(n)) / elapsed),
        "sent": dict(sent),
        "queries": len(replies),
        "replies": dict(codes),
        "replies_per_query": dict(Counter(len(r) for r in replies.values())),
        "accepted_s": {  # trajectory queries answered "ok": how long they took
            "count": len(accepted_after),
            "median": round(float(np.median(accepted_after)), 3) if accepted_after else None,
            "max": round(max(accepted_after), 3) if accepted_after else None,
        },
    }


# -- the daemon (this process) -----------------------------------------------------------------


class LagProbe:
    """How late a 1 kHz timerfd callback runs on the loop: how long the loop was kept
    from its callbacks (the cycle's own jitter is folded into one period)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._timer = PeriodicTimer(1e-3)
        self._served = 0
        self.lateness: list[float] = []
        loop.add_reader(self._timer.fileno(), self._tick)

    def _tick(self) -> None:
        n = self._timer.expirations()
        if n:
            due = self._timer.start + self._served * self._timer.period  # oldest unserved
            self.lateness.append(time.monotonic() - due)
            self._served += n

    def figures(self) -> dict[str, float]:
        """p50/p99/max (µs) and the share of ticks served more than 0.5 ms late (%)."""
        lateness, self.lateness = np.array(self.lateness) * 1e6, []
        return {
            "p50_us": round(float(np.median(lateness)), 1),
            "p99_us": round(float(np.percentile(lateness, 99)), 1),
            "max_us": round(float(lateness.max()), 1),
            "over_500us_pct": round(100.0 * float(np.mean(lateness > 500.0)), 2),
        }

    def close(self) -> None:
        self._loop.remove_reader(self._timer.fileno())
        self._timer.close()


def cycle_figures(stats: CycleStats) -> dict[str, float]:
    summary = stats.summary()
    out: dict[str, float] = {"cycles": stats.cycles}
    for name in ("jitter", "compute", "latency"):
        for key, value in summary[name].items():
            out[f"{name}_{key}"] = value
    per = 1e4 / max(stats.cycles, 1)
    out["deadline_misses_per_1e4"] = round(stats.deadline_misses * per, 2)
    out["overruns_per_1e4"] = round(stats.overruns * per, 2)
    return out


async def measure(seconds: float, rate: float, mix: str, limit: float | None) -> dict[str, Any]:
    """Set up, then the quiet and the flood phase; what it measured.  If the robot braked
    before the flood (a host too busy even without one), "braked_before" says in which
    phase and there are no flood figures."""
    endpoint = free_endpoint()

    def edit(data: dict) -> None:
        data["zenoh"]["listen"] = [endpoint]
        if limit is not None:
            data["zenoh"]["ingress_limits_hz"] = {"trajectory": limit, "cmd/*": limit}

    config = load_config(CONFIG, edit)
    load_checks(config)  # the planner's compiled checks, loaded before the cycle runs
    prefix = config.zenoh.key_prefix(config.robot.name)
    out: dict[str, Any] = {}

    def braked(service: Service, phase: str) -> bool:
        if service.machine.state in (SafetyState.HOLD, SafetyState.TRACKING):
            return False
        fault = service.machine.fault
        out["braked_before"] = phase
        out["fault"] = None if fault is None else fault.line()
        return True

    async def phases(service: Service) -> None:
        await service.command("enable", {})
        tracking = parse_trajectory(tracking_trajectory(2 * seconds + 30.0))
        await Planner(config, LocalLink(service)).submit_trajectory(tracking, None)  # set-up
        await asyncio.sleep(1.0)
        if braked(service, "setup"):
            return
        probe = LagProbe(asyncio.get_running_loop())
        service.stats = CycleStats(config.controller.rate_hz)
        await asyncio.sleep(seconds)
        out["quiet"] = cycle_figures(service.stats)
        out["quiet"]["loop_lag"] = probe.figures()
        if braked(service, "quiet"):
            return
        processes = {"core": psutil.Process(), "companion": _companion()}
        before = {name: proc.memory_info().rss for name, proc in processes.items()}
        peak = dict(before)
        service.stats = CycleStats(config.controller.rate_hz)
        flooder = asyncio.ensure_future(
            ordinary_child(
                __file__,
                *("--flooder", endpoint, "--prefix", prefix, "--seconds", str(seconds)),
                *("--rate", str(rate), "--mix", mix),
            )
        )
        while not flooder.done():
            for name, proc in processes.items():
                peak[name] = max(peak[name], proc.memory_info().rss)
            await asyncio.wait([flooder], timeout=0.05)
        out["flood"] = cycle_figures(service.stats)
        out["flood"]["loop_lag"] = probe.figures()
        probe.close()
        out["rss_mb"] = {
            name: {
                "before": round(before[name] / 2**20, 1),
                "peak": round(peak[name] / 2**20, 1),
                "after": round(proc.memory_info().rss / 2**20, 1),
            }
            for name, proc in processes.items()
        }
        out["state_after"] = service.machine.state.value
        fault = service.machine.fault
        out["fault"] = None if fault is None else fault.line()
        out["flooder"] = flooder.result()
        out["frames"] = service.state()["frames"]

    await InProcessSimulator(config).serve(after_start=phases)
    return out


def _companion() -> psutil.Process:
    """The companion process of the daemon this process runs."""
    for child in psutil.Process().children():
        if "daemon.process.companion" in " ".join(child.cmdline()):
            return child
    raise SystemExit("the daemon has no companion process")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=5.0, help="per phase")
    parser.add_argument("--rate", type=float, default=2000.0, help="puts per second")
    parser.add_argument("--mix", choices=MIXES, default="refused")
    parser.add_argument("--limit", type=float, help="ingress limit (Hz) per limited key")
    parser.add_argument("--flooder", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--prefix", default=PREFIX, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.flooder:
        print(json.dumps(flooder(args.flooder, args.prefix, args.seconds, args.rate, args.mix)))
        return
    out = asyncio.run(measure(args.seconds, args.rate, args.mix, args.limit))
    out["setup"] = {
        "seconds": args.seconds,
        "rate": args.rate,
        "mix": args.mix,
        "limit": args.limit,
    }
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
