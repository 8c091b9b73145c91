"""Benchmark of the zenoh interface (daemon/interface/zenoh_io.py) against a STAND-IN handler.

The daemon side runs in a child process: the ZenohInterface on its own asyncio loop with
a stand-in DaemonHandler that accepts every trajectory at once and returns an 8-cable
state snapshot (no robot, no controller, no validation along the path).  The parent is
a planner with a plain zenoh client session on tcp/127.0.0.1.  It measures:

- accept_latency: a 100-waypoint trajectory put on <prefix>/trajectory until its
  trajectory_accepted event arrives: the size check and copy in the child's zenoh
  thread, the hand-over to the loop, JSON decoding, schema check and spline build in the
  interface's parse thread (which pauses every 0.2 ms for the loop),
  the handler on the loop, the event back.  Trials are --gap seconds apart, a planner's
  pace: back to back they would exceed the parse thread's CPU budget in a flood (a
  quarter of a core after half a second of parsing) and measure that limit instead;
- accept_latency_query: the same trajectory sent as a get, until the reply;
- large_accept: a --large-waypoint trajectory (10,000 by default, the default
  max_waypoints) put until its trajectory_accepted event, --large-trials times 1 s apart
  (median and max, s); and what it costs the child's loop meanwhile: a 1 kHz timerfd on
  the interface's loop, read as a control cycle on that loop would read it, counts the ticks
  that came a whole period late or more ("missed_cycles", with "idle_missed_cycles" over
  as long a time with nothing to parse: the host's own floor) and the longest lag;
- state_jitter: |interval - period| between successive state publications, from the
  publication times the state messages carry (the child's clock: loop timing only);
- state_arrival_jitter: the same from the times the parent receives them.

    python bench/zenoh_io.py [--json] [--trials N] [--gap S] [--seconds S] [--rate HZ]
                             [--large N] [--large-trials N]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np
import zenoh
from timing import free_endpoint, print_timings, summary_us

from daemon.config.zenoh_config import ZenohSettings, client_zenoh_config
from daemon.interface.zenoh_io import ZenohInterface
from daemon.process.heap import freeze_start_up, reuse_freed_memory
from drivers.clock import PeriodicTimer

PREFIX = "cdpr/bench"


TICK = 1e-3  # s: the loop ticker's period (a 1 kHz control cycle)


class Ticker:
    """A 1 kHz timerfd on the child's loop, read as the real-time core reads its cycle's
    (drivers.clock.PeriodicTimer through loop.add_reader): how late each tick is taken.
    Not asyncio.sleep: it wakes at whole milliseconds (epoll's timeout), and a ticker on
    it counted some 120 of every 1,000 ticks a period late with nothing to parse."""

    def __init__(self) -> None:
        self.missed = 0  # ticks a whole period late or more, since the last read
        self.longest = 0.0  # s, the same
        self._timer: PeriodicTimer | None = None

    def start(self) -> None:
        self._timer = PeriodicTimer(TICK)
        asyncio.get_running_loop().add_reader(self._timer.fileno(), self._tick)

    def _tick(self) -> None:
        assert self._timer is not None
        expired = self._timer.expirations()
        if expired == 0:
            return
        now = time.monotonic()
        self.missed += expired - 1  # periods that passed with no tick taken
        late = self._timer.lateness(now, expired)
        self.longest = max(self.longest, late)

    def stop(self) -> None:
        if self._timer is not None:
            asyncio.get_running_loop().remove_reader(self._timer.fileno())
            self._timer.close()

    def read(self) -> dict[str, float]:
        """The counts since the last read, and start again."""
        out = {"missed_cycles": self.missed, "longest_lag_ms": round(self.longest * 1e3, 2)}
        self.missed, self.longest = 0, 0.0
        return out


class StandIn:
    """Accepts everything at once; a state snapshot the size of an 8-cable robot's; the
    status command reads the loop ticker."""

    def __init__(self, ticker: Ticker) -> None:
        self.ticker = ticker

    def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        return {"state": "IDLE", **self.ticker.read()}

    def submit_trajectory(self, trajectory: Any, start: float | None, claim: Any) -> dict[str, Any]:
        return {"accepted": True, "duration": trajectory.duration}

    async def slack(self) -> None:
        return  # no control cycle here

    def state(self) -> dict[str, Any]:
        return {
            "state": "TRACKING",
            "fault": None,
            "conditions": [],
            "pose": {
                "position": [0.1, 0.0, 1.3],
                "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
            },
            "twist": [0.05, 0.0, 0.0, 0.0, 0.0, 0.0],
            "lengths": [1.9 + 0.01 * k for k in range(8)],
            "rates": [0.01] * 8,
            "tensions": [61.0 + k for k in range(8)],
            "forces": [-61.0 - k for k in range(8)],
            "cycle": {"rate_hz": 500.0, "last_us": 180.0, "p99_us": 260.0, "overruns": 0},
        }


def serve(endpoint: str, rate_hz: float) -> None:
    """The child: serve until the parent closes our stdin, with the companion's memory
    settings (daemon.process.heap: the start-up heap frozen out of the collector's scans,
    without which a full collection during a long parse held the GIL 30-45 ms)."""
    reuse_freed_memory()
    freeze_start_up()

    async def run() -> None:
        settings = ZenohSettings(listen=[endpoint], state_rate_hz=rate_hz)
        ticker = Ticker()
        ticker.start()
        async with ZenohInterface(settings, StandIn(ticker), PREFIX):
            await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
        ticker.stop()

    asyncio.run(run())


def trajectory_json(n: int = 100) -> dict[str, Any]:
    """n waypoints 0.1 s apart along a slow circle with a slow yaw: valid and smooth."""
    waypoints = []
    for k in range(n):
        angle = 0.02 * k
        waypoints.append(
            {
                "t": 0.1 * k,
                "position": [0.1 * math.cos(angle), 0.1 * math.sin(angle), 1.25],
                "quaternion": {
                    "w": math.cos(angle / 4),
                    "x": 0.0,
                    "y": 0.0,
                    "z": math.sin(angle / 4),
                },
            }
        )
    return {"version": 1, "waypoints": waypoints}


def connect(endpoint: str, within: float = 20.0) -> zenoh.Session:
    """A client session once the child's interface is up (its liveliness token)."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            session = zenoh.open(client_zenoh_config([endpoint]))
        except zenoh.ZError:  # not listening yet
            time.sleep(0.1)
            continue
        if list(session.liveliness().get(f"{PREFIX}/alive", timeout=1.0)):
            return session
        session.close()
    raise SystemExit(f"the interface did not come up on {endpoint}")


def jitter(times: list[float], period: float) -> np.ndarray:
    """|interval - period| in nanoseconds."""
    return np.abs(np.diff(np.array(times)) - period) * 1e9


def status(session: zenoh.Session) -> dict[str, Any]:
    """The stand-in's status: the loop ticker's counts since the last status."""
    replies = list(session.get(f"{PREFIX}/cmd/status", timeout=5.0))
    if not (replies and replies[0].ok is not None):
        raise SystemExit("no status reply")
    return json.loads(replies[0].ok.payload.to_bytes())["result"]


def measure(
    endpoint: str,
    trials: int,
    gap: float,
    seconds: float,
    rate_hz: float,
    large: int,
    large_trials: int,
) -> dict[str, Any]:
    body = trajectory_json()
    accepted: dict[str, float] = {}
    arrived = threading.Condition()
    stamps: list[tuple[float, float]] = []  # (publication time, arrival time)

    def on_event(sample: zenoh.Sample) -> None:
        event = json.loads(sample.payload.to_bytes())
        if event.get("event") == "trajectory_accepted":
            with arrived:
                accepted[event["id"]] = time.perf_counter()
                arrived.notify()

    def on_state(sample: zenoh.Sample) -> None:
        stamps.append((json.loads(sample.payload.to_bytes())["time"], time.perf_counter()))

    with connect(endpoint) as session:
        events = session.declare_subscriber(f"{PREFIX}/events", on_event)
        publisher = session.declare_publisher(f"{PREFIX}/trajectory")
        list(session.get(f"{PREFIX}/cmd/status", timeout=5.0))  # subscription in place
        put_ns = np.empty(trials)
        for i in range(trials):
            ident = f"put-{i}"
            payload = json.dumps({**body, "id": ident})
            t0 = time.perf_counter()
            publisher.put(payload)
            with arrived:
                if not arrived.wait_for(lambda ident=ident: ident in accepted, timeout=5.0):
                    raise SystemExit(f"no trajectory_accepted event for {ident}")
            put_ns[i] = (accepted[ident] - t0) * 1e9
            time.sleep(gap)
        query_ns = np.empty(trials)
        for i in range(trials):
            payload = json.dumps({**body, "id": f"get-{i}"})
            t0 = time.perf_counter()
            replies = list(session.get(f"{PREFIX}/trajectory", payload=payload, timeout=5.0))
            query_ns[i] = (time.perf_counter() - t0) * 1e9
            if not (replies and replies[0].ok is not None):
                raise SystemExit("a trajectory query was not accepted")
            time.sleep(gap)
        large_s, missed, idle_missed, longest = [], 0, 0, 0.0
        payload = json.dumps({**trajectory_json(large), "id": "large"})
        for i in range(large_trials):
            status(session)
            time.sleep(1.0)
            idle_missed += status(session)["missed_cycles"]  # the host's own floor
            ident = f"large-{i}"
            t0 = time.perf_counter()
            publisher.put(payload.replace('"id": "large"', f'"id": "{ident}"'))
            with arrived:
                if not arrived.wait_for(lambda ident=ident: ident in accepted, timeout=60.0):
                    raise SystemExit(f"no trajectory_accepted event for {ident}")
            large_s.append(accepted[ident] - t0)
            time.sleep(max(0.0, 1.0 - large_s[-1]))  # as long a window as the idle one
            ticks = status(session)
            missed += ticks["missed_cycles"]
            longest = max(longest, ticks["longest_lag_ms"])
        events.undeclare()
        state = session.declare_subscriber(f"{PREFIX}/state", on_state)
        time.sleep(seconds)
        state.undeclare()
    period = 1.0 / rate_hz
    return {
        "accept_latency": summary_us(put_ns),
        "accept_latency_query": summary_us(query_ns),
        "large_accept": {
            "waypoints": large,
            "payload_bytes": len(payload),
            "median_s": round(float(np.median(large_s)), 3),
            "max_s": round(max(large_s), 3),
            "missed_cycles": missed,
            "idle_missed_cycles": idle_missed,
            "longest_lag_ms": longest,
            "trials": large_trials,
        },
        "state_jitter": summary_us(jitter([s[0] for s in stamps], period)),
        "state_arrival_jitter": summary_us(jitter([s[1] for s in stamps], period)),
        "setup": {
            "handler": "stand-in (no robot, no validation)",
            "waypoints": len(body["waypoints"]),
            "payload_bytes": len(json.dumps(body)),
            "trials": trials,
            "gap_s": gap,
            "state_rate_hz": rate_hz,
            "state_messages": len(stamps),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--trials", type=int, default=100, help="trajectories per path")
    parser.add_argument("--gap", type=float, default=0.1, help="s between trajectories")
    parser.add_argument("--seconds", type=float, default=5.0, help="state sampling time")
    parser.add_argument("--rate", type=float, default=50.0, help="state rate (Hz)")
    parser.add_argument("--large", type=int, default=10_000, help="waypoints of the long one")
    parser.add_argument("--large-trials", type=int, default=3, help="long trajectories sent")
    parser.add_argument("--serve", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.serve, args.rate)
        return
    endpoint = free_endpoint()
    child = subprocess.Popen(
        [sys.executable, __file__, "--serve", endpoint, "--rate", str(args.rate)],
        stdin=subprocess.PIPE,
    )
    try:
        results = measure(
            endpoint, args.trials, args.gap, args.seconds, args.rate, args.large, args.large_trials
        )
    finally:
        child.stdin.close()
        child.wait(timeout=20)
    if args.json:
        print(json.dumps(results))
    else:
        print(f"stand-in handler; setup: {results.pop('setup')}")
        print(f"large_accept: {results.pop('large_accept')}")
        print_timings(results)


if __name__ == "__main__":
    main()
