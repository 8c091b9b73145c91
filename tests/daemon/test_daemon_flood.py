"""A zenoh flood against a RUNNING daemon (`cdprd run --sim`, its own process) while the
robot tracks a trajectory (DESIGN §9-§10).

Another process (bench/flood.py --flooder, mix "all") puts ~2000 messages a second on
<prefix>/trajectory for a few seconds — valid trajectories (short moves near home, and
100-waypoint circles) that the service accepts while the robot moves, 100-waypoint
trajectories that parse but start in the past (so the service refuses them after the
whole decoding cost), malformed, deeply nested, oversized and ~2 MB ones — and sends a
command or trajectory query every tenth put.  The daemon must keep control (never
BRAKED: a stalled loop would let the drives' 50 ms watchdogs or the stale-feedback check
brake it, and a jump of the reference the tracking-error bound), answer every query
exactly once (possibly "busy"), keep its queues within their depth and its memory
bounded, and account for every message in the published `interface` counters.  Timing
figures are bench/flood.py's business, not asserted here.
"""

from __future__ import annotations

import asyncio
import json
import math
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml
import zenoh

from cdpr.trajectory import TrajectoryLimits, parse_trajectory
from daemon.config.zenoh_config import ZenohSettings, client_zenoh_config
from daemon.interface import messages, zenoh_io
from daemon.interface.messages import (
    JSON_PIECE,
    ONE_PIECE_JSON_BYTES,
    _decode_in_pieces,
    check_trajectory_head,
    decode_json,
    parse_waypoints,
)
from daemon.service.api import CommandError
from tests.loopback import free_port

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
FLOODER = ROOT / "bench" / "flood.py"
PREFIX = "cdpr/reference8"
QUEUE_DEPTH = 16  # the default zenoh.queue_depth
SECONDS = 3.0  # of flood
RATE = 2000.0  # puts per second
RSS_BOUND = 96 * 2**20  # queues of raw payloads (16 x 2 MiB), one decoded ~2 MB message


def wait_for(condition: Any, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.02)


def ask(session: zenoh.Session, key: str, body: dict | None = None) -> dict:
    payload = None if body is None else json.dumps(body)
    replies = list(session.get(f"{PREFIX}/{key}", payload=payload, timeout=10.0))
    assert len(replies) == 1, f"{key}: {len(replies)} replies"
    sample = replies[0].ok if replies[0].ok is not None else replies[0].err
    return json.loads(sample.payload.to_bytes())


def balanced(counters: dict[str, int]) -> bool:
    """Every message received is accounted for: refused, dropped or decided, and every
    query answered (or its querier gone)."""
    c = {key: counters.get(key, 0) for key in COUNTERS}
    received = c["trajectory_puts"] + c["trajectory_queries"]
    decided = (
        c["trajectories_refused"]
        + c["trajectories_queue_dropped"]
        + c["trajectories_accepted"]
        + c["trajectories_rejected"]
    )
    queries = c["trajectory_queries"] + c["command_queries"]
    return received == decided and queries == c["replies"] + c["replies_failed"]


COUNTERS = (
    "trajectory_puts",
    "trajectory_queries",
    "command_queries",
    "trajectories_refused",
    "trajectories_queue_dropped",
    "trajectories_accepted",
    "trajectories_rejected",
    "replies",
    "replies_failed",
)


def slow_circle(seconds: float) -> dict:
    """Tracked through the whole flood: a 3 cm circle in 8 s, back home at rest."""
    waypoints = []
    for k in range(int(seconds / 0.5) + 1):
        angle = 2.0 * math.pi * k / 16
        waypoints.append(
            {
                "t": 0.5 * k,
                "position": [0.03 * math.sin(angle), 0.03 * (1.0 - math.cos(angle)), 1.25],
                "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
            }
        )
    return {"version": 1, "id": "tracking", "waypoints": waypoints}


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_flood_leaves_the_running_daemon_in_control(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [endpoint]
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    log = (tmp_path / "daemon.log").open("w")  # a file: a full pipe would stall the daemon
    daemon = subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "run", "--config", str(config), "--sim"],
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    states: list[dict] = []
    try:
        wait_for(lambda: _connectable(port), 20.0, "the daemon to listen")
        with zenoh.open(client_zenoh_config([endpoint])) as session:
            session.declare_subscriber(
                f"{PREFIX}/state", lambda s: states.append(json.loads(s.payload.to_bytes()))
            )
            wait_for(lambda: states and states[-1]["state"] == "idle", 20.0, "IDLE")
            assert ask(session, "cmd/enable")["ok"]
            reply = ask(session, "trajectory", slow_circle(60.0))
            assert reply["ok"], reply
            wait_for(lambda: states[-1]["state"] == "tracking", 5.0, "TRACKING")
            process = psutil.Process(daemon.pid)
            rss_before = process.memory_info().rss
            first = len(states)
            done = subprocess.run(
                [sys.executable, str(FLOODER), "--flooder", endpoint, "--prefix", PREFIX,
                 "--seconds", str(SECONDS), "--rate", str(RATE), "--mix", "all"],
                capture_output=True, text=True, timeout=90, check=True,
            )  # fmt: skip
            flood = json.loads(done.stdout.splitlines()[-1])  # after its "flooding" line
            try:
                wait_for(lambda: balanced(states[-1]["interface"]), 40.0, "every decision")
            except AssertionError:
                last = states[-1]
                pytest.fail(
                    f"not every message decided: {last['interface']} (state seq {last['seq']}, "
                    f"{len(states)} states, state {last['state']})"
                )
            rss_after = process.memory_info().rss
            during = states[first:]
            counters = states[-1]["interface"]
            assert ask(session, "cmd/status")["ok"]  # still serving
    finally:
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(timeout=20)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait()
        log.close()
    output = (tmp_path / "daemon.log").read_text()
    growth = round((rss_after - rss_before) / 2**20, 1)
    figures = {"flooder": flood, "interface": counters, "rss_growth_mb": growth}
    print(json.dumps({**figures, "cycle": during[-1]["cycle"]}, indent=1))

    # in control throughout: never braked, no fault
    assert {s["state"] for s in during} <= {"tracking", "hold"}, output[-2000:]
    assert all(s["fault"] is None for s in during)
    assert daemon.returncode == 0, output[-2000:]

    # a real flood: thousands of puts a second, every one seen by the daemon
    assert flood["puts"] >= 0.8 * SECONDS * RATE
    assert counters["trajectory_puts"] == flood["puts"]
    queries = counters["command_queries"] + counters["trajectory_queries"]
    assert queries == flood["queries"] + 2  # and ours: enable, the tracking trajectory

    # every query answered exactly once, with a JSON reply (possibly "busy")
    assert flood["replies_per_query"] == {"1": flood["queries"]}
    assert not [code for code in flood["replies"] if code.startswith("not_json")]
    assert counters.get("replies_failed", 0) == counters.get("callback_errors", 0) == 0

    # bounded: queues within their depth, drops counted, memory
    for queue in ("commands", "trajectories", "events"):
        assert counters[f"{queue}_queue_high_water"] <= QUEUE_DEPTH
    assert counters["trajectories_queue_dropped"] > 0  # it did overflow ...
    assert flood["replies"].get("busy", 0) > 0  # ... and said so
    assert counters["trajectories_refused"] > 0  # bad input, by the interface
    assert counters["trajectories_rejected"] > 0  # parsed, then refused by the service
    assert counters["trajectories_accepted"] > 1  # ours, and flood trajectories while moving
    assert rss_after - rss_before < RSS_BOUND


def _connectable(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


# -- the pieces that keep a flood off the loop ----------------------------------------------


def random_json(rng: random.Random, budget: int, depth: int = 0) -> Any:
    """A random JSON value of roughly `budget` leaves: strings long and short, numbers
    of every kind, nesting."""
    if budget <= 1 or depth > 8 or rng.random() < 0.3:
        return rng.choice(
            [0, -7, 12345678901234567890, 2.5e-300, -1.5, True, None, "", 'é\\n"\t', "s" * 3000]
        )
    if rng.random() < 0.5:
        return [random_json(rng, budget // 6, depth + 1) for _ in range(rng.randint(0, 12))]
    return {f"k{rng.randint(0, 40)}": random_json(rng, budget // 6, depth + 1)
            for _ in range(rng.randint(0, 12))}  # fmt: skip


def outcome(decode: Any, text: str) -> Any:
    try:
        return decode(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError
        return type(exc).__name__


def test_long_json_decodes_in_pieces_exactly_as_json_loads() -> None:
    rng = random.Random(7)
    checked = 0
    while checked < 60:
        text = json.dumps(random_json(rng, 4000), indent=rng.choice([None, 0, 2]))
        if len(text) <= ONE_PIECE_JSON_BYTES:
            continue
        checked += 1
        assert _decode_in_pieces(text) == json.loads(text)
        for _ in range(4):  # and the same verdict on a corrupted copy
            k = rng.randrange(len(text))
            bad = text[:k] + rng.choice(["", ",", "]", "}", '"', "x", "[", ":"]) + text[k + 1 :]
            assert outcome(_decode_in_pieces, bad) == outcome(json.loads, bad), bad[k - 30 : k + 30]


@pytest.mark.parametrize(
    ("payload", "words"),
    [
        (b'{"waypoints": "' + b"x" * 40_000 + b'"}', "longer than 16384 characters"),
        (b'{"' + b"k" * 40_000 + b'": 1}', "longer than 16384 characters"),
        (b"[0." + b"1" * 40_000 + b"]", "longer than 16384 characters"),
        (b"[" + b"1, " * 20_000 + b"NaN]", "NaN is not a JSON number"),
        (b"[" * 40_000 + b"]" * 40_000, "nested too deeply"),
        (b"[" + b" " * 40_000 + b"1 2]", "Expecting ',' delimiter"),
        (b'{"a": [' + b"1, " * 20_000 + b"1] " + b" " * 40_000 + b"}}", "Extra data"),
    ],
    ids=["string", "key", "number", "nan", "nesting", "delimiter", "extra"],
)
def test_long_json_is_refused_naming_the_problem(payload: bytes, words: str) -> None:
    with pytest.raises(CommandError) as info:
        decode_json(payload, 1 << 20)
    assert info.value.code == "bad_request" and words in info.value.reason


def test_the_c_decoder_never_gets_a_long_piece(monkeypatch: pytest.MonkeyPatch) -> None:
    """What keeps the GIL: no call of the C decoder reads more than JSON_PIECE chars."""
    seen: list[int] = []
    decoder = messages._DECODER

    class Recording:
        def decode(self, text: str) -> Any:
            seen.append(len(text))
            return decoder.decode(text)

        def raw_decode(self, text: str) -> Any:
            seen.append(len(text))
            return decoder.raw_decode(text)

    monkeypatch.setattr(messages, "_DECODER", Recording())
    body = {"id": "x" * 100, "waypoints": [waypoint(0.1 * k) for k in range(3000)]}
    payload = json.dumps(body).encode()
    assert len(payload) > 10 * JSON_PIECE
    assert decode_json(payload, 1 << 22) == body
    assert seen and max(seen) <= JSON_PIECE


def test_long_json_calls_its_checkpoint_before_each_value_and_stops_where_it_raises() -> None:
    """The parse thread pauses between pieces (decode_json's checkpoint): called before
    each value it reads, and what the checkpoint raises stops the decode there."""
    body = {"waypoints": [waypoint(0.1 * k) for k in range(3000)]}
    payload = json.dumps(body).encode()
    calls: list[None] = []
    assert decode_json(payload, 1 << 22, lambda: calls.append(None)) == body
    assert len(calls) >= len(body["waypoints"])

    class StoppedError(Exception):
        pass

    def stop_at_the_tenth() -> None:
        calls.append(None)
        if len(calls) == 10:
            raise StoppedError

    calls.clear()
    with pytest.raises(StoppedError):
        decode_json(payload, 1 << 22, stop_at_the_tenth)
    assert len(calls) == 10


def test_head_then_waypoints_is_the_whole_message() -> None:
    """The head keeps the id and start apart; the waypoints parse as cdpr parses them."""
    limits = TrajectoryLimits(max_waypoints=50)
    waypoints = [waypoint(0.0), waypoint(1.0, 1.3)]
    body = {"id": "p", "start": 1.7e9, "waypoints": waypoints}
    head = check_trajectory_head(body, limits)
    assert (head.id, head.start, head.waypoints) == ("p", 1.7e9, 2)
    assert "id" not in head.body and "start" not in head.body
    split = parse_waypoints(head, limits)
    assert (split.id, split.start) == ("p", 1.7e9)
    whole = parse_trajectory({"waypoints": waypoints}, limits)
    assert split.trajectory.as_dict() == whole.as_dict()
    with pytest.raises(CommandError, match="51 waypoints exceed the limit of 50"):
        check_trajectory_head({"waypoints": [waypoint(k) for k in range(51)]}, limits)


def waypoint(t: float, z: float = 1.25) -> dict:
    return {"t": t, "position": [0.0, 0.0, z], "quaternion": {"w": 1, "x": 0, "y": 0, "z": 0}}


class Handler:
    """A DaemonHandler whose verdicts and long commands wait for `release`."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.running: Counter[str] = Counter()  # verdicts / long commands running now
        self.most_running: Counter[str] = Counter()
        self.calls: list[str] = []

    async def _wait(self, kind: str) -> dict[str, Any]:
        self.running[kind] += 1
        self.most_running[kind] = max(self.most_running[kind], self.running[kind])
        await self.release.wait()
        self.running[kind] -= 1
        return {"done": True}

    async def _plan(self) -> dict[str, Any]:
        await asyncio.sleep(0)  # a hold plans its stop between cycles: awaitable, short
        return {"state": "hold"}

    def command(self, name: str, args: dict[str, Any]) -> Any:
        self.calls.append(name)
        if name == "hold":
            return self._plan()
        return self._wait("command") if name in ("enable", "goto") else {"state": "hold"}

    def submit_trajectory(self, trajectory: Any, start: float | None, claim: Any) -> Any:
        self.calls.append(f"trajectory {len(trajectory.waypoints)}")
        return self._wait("trajectory")

    async def slack(self) -> None:
        return  # no control cycle here

    def state(self) -> dict[str, Any]:
        return {"state": "hold"}


def test_trajectories_one_at_a_time_parsed_off_the_loop_and_long_commands_singly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    parsed_on: list[tuple[int, int]] = []  # (waypoints, thread)

    def recording(message: Any, limits: Any) -> Any:
        parsed_on.append((message.waypoints, threading.get_ident()))
        return parse_waypoints(message, limits)

    monkeypatch.setattr(zenoh_io, "parse_waypoints", recording)
    handler = Handler()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = ZenohSettings(listen=[endpoint])
    replies: list[dict] = []

    def on_reply(reply: zenoh.Reply) -> None:
        sample = reply.ok if reply.ok is not None else reply.err
        replies.append(json.loads(sample.payload.to_bytes()))

    async def scenario() -> None:
        loop_thread = threading.get_ident()
        async with zenoh_io.ZenohInterface(settings, handler, "cdpr/t") as interface:
            with zenoh.open(client_zenoh_config([endpoint])) as session:
                two = {"waypoints": [waypoint(0.0), waypoint(1.0)]}
                many = {"waypoints": [waypoint(0.1 * k) for k in range(100)]}
                for body in (many, two, many):
                    session.put("cdpr/t/trajectory", json.dumps(body))
                session.get("cdpr/t/cmd/enable", on_reply, timeout=10.0)
                await until(lambda: handler.calls.count("enable") == 1)
                # goto waits for enable: busy; status and hold never wait for the slot
                for name in ("goto", "status", "hold"):
                    body = json.dumps({"position": [0, 0, 1]}) if name == "goto" else None
                    session.get(f"cdpr/t/cmd/{name}", on_reply, payload=body, timeout=10.0)
                await until(lambda: len(replies) == 3)
                # the first is submitted once parsed (in a thread at the lowest priority:
                # seconds on a busy host); the others wait for its verdict
                await until(lambda: "trajectory 100" in handler.calls, 30.0)
                await asyncio.sleep(0.3)
                assert [c for c in handler.calls if c.startswith("trajectory")] == [
                    "trajectory 100"
                ]
                handler.release.set()
                await until(lambda: len(replies) == 4)
                await until(lambda: interface.stats().get("trajectories_accepted") == 3)
                stats = interface.stats()
        assert handler.most_running == {"command": 1, "trajectory": 1}  # one at a time
        assert [c for c in handler.calls if c.startswith("trajectory")] == [
            "trajectory 100", "trajectory 2", "trajectory 100"
        ]  # fmt: skip
        assert sorted(w for w, _ in parsed_on) == [2, 100, 100]
        for waypoints, thread in parsed_on:
            assert (thread == loop_thread) is (waypoints == 2)
        codes = {r["command"]: r.get("error", {}).get("code") for r in replies}
        assert codes == {"goto": "busy", "status": None, "hold": None, "enable": None}
        assert handler.calls.count("goto") == 1  # called, but its coroutine never started
        assert stats["commands_busy"] == 1 and stats["replies"] == 4

    asyncio.run(scenario())


def test_a_request_that_preempts_is_never_turned_away_busy() -> None:
    """While enable holds the slot of the commands that wait, a goto is answered busy and
    never started; the same goto saying preempt runs (it replaces what runs:
    daemon.service.motion decides)."""
    handler = Handler()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    replies: list[dict] = []

    def on_reply(reply: zenoh.Reply) -> None:
        sample = reply.ok if reply.ok is not None else reply.err
        replies.append(json.loads(sample.payload.to_bytes()))

    async def scenario() -> None:
        settings = ZenohSettings(listen=[endpoint])
        async with zenoh_io.ZenohInterface(settings, handler, "cdpr/t"):
            with zenoh.open(client_zenoh_config([endpoint])) as session:
                session.get("cdpr/t/cmd/enable", on_reply, timeout=10.0)
                await until(lambda: handler.running["command"] == 1)
                for preempt in (False, True):
                    body = {"position": [0, 0, 1], "client": "B", "preempt": preempt}
                    session.get("cdpr/t/cmd/goto", on_reply, payload=json.dumps(body))
                await until(lambda: len(replies) == 1 and handler.running["command"] == 2)
                handler.release.set()
                await until(lambda: len(replies) == 3)
        assert replies[0]["command"] == "goto" and replies[0]["error"]["code"] == "busy"
        assert [r["ok"] for r in replies[1:]] == [True, True]

    asyncio.run(scenario())


async def until(condition: Any, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        await asyncio.sleep(0.01)
