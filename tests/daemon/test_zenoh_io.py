"""The zenoh interface against a stand-in handler, on loopback only (DESIGN §10, §14).

A plain-zenoh client in a separate process drives it; hostile input is refused with a
clear reply and never reaches the handler; the queues stay bounded under a flood; the
config never enables multicast or gossip; the CLI client's exit codes.
"""

from __future__ import annotations

import asyncio
import ctypes
import itertools
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot
from cdpr.description import ConfigError, load_yaml, validate_section
from cdpr.trajectory import Trajectory, TrajectoryError, parse_trajectory
from daemon.cli import main
from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import (
    ZenohSettings,
    build_zenoh_config,
    client_zenoh_config,
    is_local,
)
from daemon.interface import zenoh_io
from daemon.interface.client import CdprClient, ClientError, RequestError, UnreachableError
from daemon.interface.messages import JSON_PIECE, decode_trajectory
from daemon.interface.ros2_bridge import Ros2Bridge, ingress_limits
from daemon.interface.zenoh_io import PARSE_SHARE, ZenohInterface
from daemon.service.api import Claim, CommandError
from tests.loopback import free_port

PREFIX = "cdpr/standin"
IDENTITY = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
TRAJECTORY = {
    "version": 1,
    "waypoints": [
        {"t": 0.0, "position": [0.0, 0.0, 1.25], "quaternion": IDENTITY},
        {"t": 2.0, "position": [0.1, 0.0, 1.3], "quaternion": IDENTITY},
    ],
}
PR_GET_TIMERSLACK = 30  # <linux/prctl.h>
WAIT = 10.0  # s: upper bound on every wait for the other side (never reached when healthy)


class StandIn:
    """A DaemonHandler that records what reaches it (and on which thread)."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.threads: set[int] = set()
        self.refuse_enable = True
        self.delay = 0.0  # s of busy work per call (to make the loop the bottleneck)
        self.state_calls = 0
        self.slack_waits = 0
        self.pose: Pose | None = Pose((0.0, 0.0, 1.25))  # None: no pose (idle, braked)
        self.tensions = [float("nan")] * 8
        self.sinks: list[Callable[[dict[str, Any]], None]] = []  # subscribed to its events

    def _record(self, *call: Any) -> None:
        self.threads.add(threading.get_ident())
        self.calls.append(call)
        if self.delay:
            end = time.perf_counter() + self.delay
            while time.perf_counter() < end:
                pass

    def command(self, name: str, args: dict[str, Any]) -> Any:
        self._record(name, args)
        if name == "enable" and self.refuse_enable:
            raise CommandError("invalid_state", "cannot enable while BRAKED (reset first)")
        if name == "reset":

            async def wait_for_drives() -> dict[str, Any]:
                await asyncio.sleep(0.05)
                return {"state": "IDLE"}

            return wait_for_drives()
        return {"state": "IDLE", "command": name}

    def submit_trajectory(self, trajectory: Trajectory, start: float | None, claim: Any) -> Any:
        self._record("trajectory", trajectory, start, claim)
        if trajectory.duration > 100.0:
            raise CommandError("rejected", "too long for the stand-in", limit="max_duration")
        if trajectory.duration > 10.0:  # validated "between control cycles"

            async def validate() -> dict[str, Any]:
                await asyncio.sleep(0.05)
                return {"duration": trajectory.duration, "awaited": True}

            return validate()
        return {"duration": trajectory.duration}

    async def slack(self) -> None:
        self.slack_waits += 1  # a stand-in: no control cycle, slack at once

    def subscribe(self, sink: Callable[[dict[str, Any]], None]) -> None:
        self.sinks.append(sink)

    def state(self) -> dict[str, Any]:
        self.threads.add(threading.get_ident())
        self.state_calls += 1
        if self.pose is None:
            return {"state": "IDLE"}
        return {
            "state": "IDLE",
            "pose": self.pose.as_dict(),
            "tracking_error": [0.0] * 6,
            "tensions": list(self.tensions),
        }


class Running:
    """A ZenohInterface serving `handler` on its own event loop in a thread: with
    `settings`, or listening on a free loopback port with the `overrides`; with `ros2`,
    the ROS 2 bridge on its session too, as the companion runs them (with `robot`, its
    RViz view); `timer` times the paths it takes."""

    def __init__(
        self,
        handler: StandIn,
        settings: ZenohSettings | None = None,
        prefix: str = PREFIX,
        ros2: Ros2Settings | None = None,
        timer: Callable[[Any], Trajectory] | None = None,
        robot: Robot | None = None,
        **overrides: Any,
    ) -> None:
        if settings is None:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            settings = ZenohSettings(listen=[endpoint], **overrides)
        self.endpoint = next(iter(settings.listen_endpoints), None)
        self.settings = settings
        self.prefix = prefix
        self.ros2 = ros2
        self.handler = handler
        self.timer = timer
        self.robot = robot
        self.loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self.loop.run_until_complete, args=(self._run(),))
        self._thread.start()
        assert self._ready.wait(WAIT), "the interface did not start"

    async def _run(self) -> None:
        self.loop_thread = threading.get_ident()
        limits = {} if self.ros2 is None else ingress_limits(self.ros2, self.settings)
        self.interface = ZenohInterface(
            self.settings, self.handler, self.prefix, None, limits, self.timer
        )
        self._stop = asyncio.Event()
        await self.interface.start()
        bridge = None
        if self.ros2 is not None:
            bridge = Ros2Bridge(self.ros2, self.handler, self.interface, robot=self.robot)
            await bridge.start()
        self._ready.set()
        await self._stop.wait()
        if bridge is not None:
            await bridge.close()
        await self.interface.close()

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(WAIT)
        self.loop.close()

    def block_loop(self) -> threading.Event:
        """Hold the event loop until the returned event is set (a stalled control cycle)."""
        release, held = threading.Event(), threading.Event()

        def hold() -> None:
            held.set()
            release.wait(WAIT)

        self.loop.call_soon_threadsafe(hold)
        assert held.wait(WAIT)
        return release

    def session(self) -> zenoh.Session:
        assert self.endpoint is not None
        return zenoh.open(client_zenoh_config([self.endpoint]))


@pytest.fixture
def running() -> Iterator[Running]:
    served = Running(StandIn())
    yield served
    served.stop()


def ask(session: zenoh.Session, key: str, payload: bytes | str | None = None) -> dict:
    """One query; the decoded reply with "zenoh_ok" telling reply from reply_err."""
    replies = list(session.get(f"{PREFIX}/{key}", payload=payload, timeout=WAIT))
    assert len(replies) == 1, f"{key}: {len(replies)} replies"
    reply = replies[0]
    sample = reply.ok if reply.ok is not None else reply.err
    body = json.loads(sample.payload.to_bytes())
    return {**body, "zenoh_ok": reply.ok is not None}


def alive_tokens(session: zenoh.Session) -> list[str]:
    """The daemons' alive tokens a session sees (cdpr/<robot>/alive), sorted."""
    tokens = session.liveliness().get("cdpr/*/alive", timeout=WAIT)
    return sorted(str(r.ok.key_expr) for r in tokens if r.ok is not None)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.005)


# -- (1) a separate process with the plain zenoh API --------------------------------------

PLAIN_CLIENT = r"""
import json, sys, time, zenoh

endpoint, prefix, trajectory = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/gossip/enabled", "false")
out = {"replies": {}, "events": [], "states": []}
decode = lambda sample: json.loads(sample.payload.to_bytes())


def ask(key, payload=None):
    for reply in session.get(prefix + "/" + key, payload=payload, timeout=10):
        sample = reply.ok if reply.ok is not None else reply.err
        return {"zenoh_ok": reply.ok is not None, **decode(sample)}


with zenoh.open(conf) as session:
    subs = [
        session.declare_subscriber(prefix + "/events", lambda s: out["events"].append(decode(s))),
        session.declare_subscriber(prefix + "/state", lambda s: out["states"].append(decode(s))),
    ]
    tokens = session.liveliness().get(prefix + "/alive", timeout=10)
    out["alive"] = [str(r.ok.key_expr) for r in tokens if r.ok is not None]
    out["replies"]["status"] = ask("cmd/status")
    out["replies"]["enable"] = ask("cmd/enable")
    out["replies"]["goto"] = ask("cmd/goto", json.dumps({"position": [0.1, 0.2, 1.3]}))
    out["replies"]["fly"] = ask("cmd/fly")
    session.put(prefix + "/trajectory", json.dumps({**trajectory, "id": "by-put"}))
    session.put(prefix + "/trajectory", b'{"id": "broken-put", "waypoints": [{"t": "0"}]}')
    out["replies"]["trajectory"] = ask("trajectory", json.dumps({**trajectory, "id": "by-get"}))
    wanted = {"by-put", "broken-put", "by-get"}
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and (
        len(out["states"]) < 3 or not wanted <= {e.get("id") for e in out["events"]}
    ):
        time.sleep(0.01)
print(json.dumps(out))
"""


def test_a_plain_zenoh_process_commands_and_sees_replies_state_and_events(
    running: Running, tmp_path: Path
) -> None:
    script = tmp_path / "plain_client.py"
    script.write_text(PLAIN_CLIENT)
    done = subprocess.run(
        [sys.executable, str(script), running.endpoint, PREFIX, json.dumps(TRAJECTORY)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    out = json.loads(done.stdout)
    replies = out["replies"]
    assert out["alive"] == [f"{PREFIX}/alive"]
    assert replies["status"] == {
        "version": 1,
        "ok": True,
        "command": "status",
        "result": {"state": "IDLE", "command": "status"},
        "zenoh_ok": True,
    }
    assert replies["enable"]["zenoh_ok"] is False  # errors come as reply_err ...
    assert replies["enable"]["error"] == {  # ... with the handler's code and reason
        "code": "invalid_state",
        "reason": "cannot enable while BRAKED (reset first)",
    }
    assert replies["goto"]["ok"] is True
    assert replies["fly"]["error"]["code"] == "unknown_command"
    assert replies["trajectory"]["id"] == "by-get"
    assert replies["trajectory"]["result"] == {"duration": 2.0}

    events = {e["id"]: e for e in out["events"]}
    assert events["by-put"]["event"] == "trajectory_accepted"
    assert events["by-get"]["event"] == "trajectory_accepted"
    assert events["broken-put"]["event"] == "trajectory_rejected"
    assert events["broken-put"]["error"] == {
        "code": "bad_request",
        "reason": "waypoint 0: schema: waypoints[0]: missing key 'position'",
        "limit": "schema",
        "waypoint": 0,
        "field": "waypoints[0].position",
    }
    assert all(e["version"] == 1 for e in out["events"])
    assert [e["seq"] for e in out["events"]] == sorted(e["seq"] for e in out["events"])

    states = out["states"]
    assert len(states) >= 3 and all(s["version"] == 1 for s in states)
    assert [s["seq"] for s in states] == sorted(s["seq"] for s in states)
    assert states[-1]["pose"]["quaternion"] == {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    assert states[-1]["tensions"] == [None] * 8  # NaN goes out as null
    assert "commands_queue_dropped" in states[-1]["interface"]

    calls = running.handler.calls
    assert [c[0] for c in calls if c[0] != "trajectory"] == ["status", "enable", "goto"]
    assert calls[2][1]["pose"] == Pose((0.1, 0.2, 1.3))
    assert sum(c[0] == "trajectory" for c in calls) == 2  # by-put and by-get, not broken-put
    assert running.handler.threads == {running.loop_thread}  # only ever on the loop thread
    # every state snapshot was taken after waiting for the control cycle's slack
    assert 0 < running.handler.state_calls <= running.handler.slack_waits


def test_a_trajectory_reaches_the_handler_with_its_senders_claim(running: Running) -> None:
    """A trajectory's "client" and "preempt" (and its id) reach the handler as its claim
    (daemon.service.motion), not the trajectory's body; without them, anonymous."""
    with running.session() as session:
        named = {**TRAJECTORY, "id": "p-1", "client": "alice@bench:1", "preempt": True}
        assert ask(session, "trajectory", json.dumps(named))["ok"]
        assert ask(session, "trajectory", json.dumps(TRAJECTORY))["ok"]
        bad = {**TRAJECTORY, "client": ""}
        assert ask(session, "trajectory", json.dumps(bad))["error"]["field"] == "client"
    claims = [c[3] for c in running.handler.calls if c[0] == "trajectory"]
    assert claims == [Claim("alice@bench:1", True, "p-1"), Claim()]


def test_awaitable_replies_and_events_from_any_thread(running: Running) -> None:
    with running.session() as session:
        seen: list[dict] = []
        sub = session.declare_subscriber(
            f"{PREFIX}/events", lambda s: seen.append(json.loads(s.payload.to_bytes()))
        )
        assert ask(session, "cmd/status")["ok"]  # the subscription is in place
        assert ask(session, "cmd/reset")["result"] == {"state": "IDLE"}  # awaited, then sent
        slow = {**TRAJECTORY, "waypoints": [TRAJECTORY["waypoints"][0], waypoint_at(20.0)]}
        reply = ask(session, "trajectory", json.dumps({**slow, "id": "slow"}))
        assert reply["result"] == {"duration": 20.0, "awaited": True}
        wait_until(lambda: any(e.get("id") == "slow" for e in seen), "the accepted event")
        threading.Thread(
            target=running.interface.publish_event, args=({"event": "fault", "why": "test"},)
        ).start()
        wait_until(lambda: any(e.get("event") == "fault" for e in seen), "the fault event")
        sub.undeclare()
    fault = next(e for e in seen if e["event"] == "fault")
    assert fault["why"] == "test" and fault["version"] == 1 and math.isfinite(fault["time"])
    with pytest.raises(ValueError, match="an event needs a name"):
        running.interface.publish_event({"kind": "fault"})


# -- (2) hostile input ---------------------------------------------------------------------


def waypoint_at(t: float) -> dict[str, Any]:
    return {**TRAJECTORY["waypoints"][1], "t": t}


def bad_trajectory(**change: Any) -> str:
    return json.dumps({**TRAJECTORY, **change})


HOSTILE_TRAJECTORIES = [
    (b"not json", "bad_request", "invalid JSON"),
    (b'{"waypoints": [NaN]}', "bad_request", "NaN is not a JSON number"),
    (b'{"waypoints": Infinity}', "bad_request", "Infinity is not a JSON number"),
    (b"[" * 20_000 + b"]" * 20_000, "bad_request", "nested too deeply"),
    (b"\xff\xfe\x00", "bad_request", "not UTF-8"),
    (b" " * 70_000, "bad_request", "exceeds the limit of 65536 bytes"),
    (b"", "bad_request", "needs a JSON payload"),
    (b"[]", "bad_request", "expected a JSON object"),
    (bad_trajectory(waypoints="many"), "bad_request", "waypoints: expected a list"),
    (bad_trajectory(waypoints=[0] * 5000), "rejected", "5000 waypoints exceed the limit of 100"),
    (bad_trajectory(version=7), "bad_request", "unsupported schema version 7"),
    (bad_trajectory(priority="high"), "bad_request", "unknown key(s) 'priority'"),
    (bad_trajectory(start=[1]), "bad_request", 'start: expected "now"'),
    (
        bad_trajectory(waypoints=[TRAJECTORY["waypoints"][1], TRAJECTORY["waypoints"][0]]),
        "rejected",
        "times",
    ),
    (
        bad_trajectory(
            waypoints=[
                TRAJECTORY["waypoints"][0],
                {**TRAJECTORY["waypoints"][1], "quaternion": {**IDENTITY, "z": 0.1}},
            ]
        ),
        "rejected",
        "unit quaternion",
    ),
    (
        bad_trajectory(waypoints=[{**TRAJECTORY["waypoints"][0], "t": "0"}]),
        "bad_request",
        "waypoints[0].t: expected a number, got str",
    ),
]

HOSTILE_COMMANDS = [
    ("cmd/fly", None, "unknown_command", "unknown command 'fly'"),
    ("cmd/*", None, "bad_request", "commands need an exact key"),
    ("cmd/**", None, "bad_request", "commands need an exact key"),
    ("cmd/enable/now", None, "unknown_command", "unknown command 'enable/now'"),
    ("cmd/enable", b'{"force": true}', "bad_request", "unknown key(s) 'force'"),
    ("cmd/status", b"[1]", "bad_request", "expected a JSON object"),
    ("cmd/disable", b"null", "bad_request", "disable: expected a JSON object, got null"),
    ("cmd/hold", b"null", "bad_request", "hold: expected a JSON object, got null"),
    ("cmd/brake", b"null", "bad_request", "brake: expected a JSON object, got null"),
    ("cmd/reset", b"null", "bad_request", "reset: expected a JSON object, got null"),
    ("cmd/hold", b"3", "bad_request", "hold: expected a JSON object, got int"),
    ("cmd/disable", b'"now"', "bad_request", "disable: expected a JSON object, got str"),
    ("cmd/goto", b'{"position": [0, 0, NaN]}', "bad_request", "NaN is not a JSON number"),
    ("cmd/goto", b'{"position": [0, 0]}', "bad_request", "expected [x, y, z]"),
    ("cmd/goto", b'{"position": [0, "0", 1]}', "bad_request", "position[1]: expected a number"),
    (
        "cmd/goto",
        b'{"position": [0, 0, 1], "quaternion": {"w": 0.5, "x": 0, "y": 0, "z": 0}}',
        "rejected",
        "unit quaternion",
    ),
    ("cmd/brake", json.dumps({"reason": "x" * 1000}).encode(), "bad_request", "brake.reason"),
    ("trajectory/x", None, None, None),  # no queryable there: no reply at all
    ("*", json.dumps(TRAJECTORY).encode(), "bad_request", "exact key"),
]


@pytest.fixture(scope="module")
def hostile() -> Iterator[tuple[Running, zenoh.Session]]:
    served = Running(StandIn(), max_message_bytes=65536, max_waypoints=100)
    session = served.session()
    yield served, session
    session.close()
    served.stop()


def test_hostile_input_is_refused_clearly_and_never_reaches_the_handler(
    hostile: tuple[Running, zenoh.Session],
) -> None:
    served, session = hostile
    before = list(served.handler.calls)
    for payload, code, words in HOSTILE_TRAJECTORIES:
        reply = ask(session, "trajectory", payload)
        assert not reply["zenoh_ok"] and not reply["ok"], payload[:40]
        assert reply["version"] == 1
        assert reply["error"]["code"] == code, payload[:40]
        assert words in reply["error"]["reason"], (payload[:40], reply["error"]["reason"])
    for key, payload, code, words in HOSTILE_COMMANDS:
        raw = list(session.get(f"{PREFIX}/{key}", payload=payload, timeout=WAIT))
        replies = [json.loads(r.err.payload.to_bytes()) for r in raw if r.err is not None]
        assert len(replies) == len(raw)
        # "*" reaches the trajectory, path and cmd/** queryables; trajectory/x nothing
        assert len(replies) == {"*": 3, "trajectory/x": 0}.get(key, 1), key
        for reply in replies:
            assert reply["error"]["code"] == code, key
            assert words in reply["error"]["reason"], (key, reply["error"]["reason"])
    assert served.handler.calls == before  # nothing reached the handler
    assert ask(session, "cmd/status")["ok"]  # and the interface still serves


def test_hostile_puts_are_refused_in_events_and_wildcard_puts_ignored(
    hostile: tuple[Running, zenoh.Session],
) -> None:
    served, session = hostile
    before = list(served.handler.calls)
    seen: list[dict] = []
    sub = session.declare_subscriber(
        f"{PREFIX}/events", lambda s: seen.append(json.loads(s.payload.to_bytes()))
    )
    assert ask(session, "cmd/status")["ok"]
    before = list(served.handler.calls)
    session.put(f"{PREFIX}/trajectory", bad_trajectory(id="bad-1", version=9))
    session.put("cdpr/*/trajectory", json.dumps({**TRAJECTORY, "id": "everyone"}))
    wait_until(lambda: {"bad-1", None} <= {e.get("id") for e in seen}, "the rejections")
    sub.undeclare()
    by_id = {e["id"]: e for e in seen}
    assert "unsupported schema version 9" in by_id["bad-1"]["error"]["reason"]
    assert "send trajectories to the exact key" in by_id[None]["error"]["reason"]
    assert served.handler.calls == before


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=6),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=16,
)
mutations = st.one_of(
    json_values,
    json_values.map(lambda v: {**TRAJECTORY, "waypoints": v}),
    st.tuples(st.sampled_from(["t", "position", "quaternion", "twist", "x"]), json_values).map(
        lambda kv: {
            **TRAJECTORY,
            "waypoints": [TRAJECTORY["waypoints"][0], {**TRAJECTORY["waypoints"][1], kv[0]: kv[1]}],
        }
    ),
)


@settings(max_examples=60)
@given(data=mutations)
def test_generated_json_is_refused_exactly_when_decoding_fails(
    hostile: tuple[Running, zenoh.Session], data: Any
) -> None:
    """Over the network, the same verdict as the decoder: refusals never call the handler."""
    served, session = hostile
    served.handler.calls.clear()
    try:
        decode_trajectory(data, served.interface.limits)
        expected = None
    except CommandError as exc:
        expected = exc.code
    reply = ask(session, "trajectory", json.dumps(data))
    if expected is None:
        assert reply["ok"] and len(served.handler.calls) == 1
    else:
        assert not reply["ok"] and reply["error"]["code"] == expected and reply["error"]["reason"]
        assert served.handler.calls == []


# -- (3) bounded queues and floods -----------------------------------------------------------


def _parse_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("cdprd-trajectory-parse")]


def test_closing_stops_a_parse_thread_waiting_for_budget() -> None:
    """After a 2 MB message the parse thread owes seconds of CPU budget and waits them
    out before the next message; a process exits only once that thread is done, so
    close() must stop it at once (the companion was killed for not exiting in 3 s)."""
    before = set(_parse_threads())  # other tests' interfaces
    served = Running(StandIn())
    try:
        with served.session() as session:
            assert ask(session, "cmd/status")["ok"]
            served.interface._parse_credit = -60.0 * PARSE_SHARE  # a minute to wait
            served.interface._credit_time = time.monotonic()
            first = TRAJECTORY["waypoints"][0]
            waypoints = [first, *(waypoint_at(1.0 + k) for k in range(4))]  # not inline
            session.put(f"{PREFIX}/trajectory", json.dumps({**TRAJECTORY, "waypoints": waypoints}))
            wait_until(lambda: bool(set(_parse_threads()) - before), "the parse thread")
            time.sleep(0.3)  # the idle thread takes the message at once, and waits
    finally:
        served.stop()
    for thread in set(_parse_threads()) - before:
        thread.join(WAIT)
        assert not thread.is_alive(), "the parse thread outlived close()"


def test_a_long_trajectory_is_decoded_with_the_hook_off_pausing_between_pieces(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The parse thread decodes long JSON with its profile hook off (a hook called at
    every call doubles the decode), the decoder calling the thread's pause checkpoint
    between pieces instead; the waypoints after it parse with the hook back on."""
    seen: list[tuple[object, object, int]] = []
    original_decode, original_parse = zenoh_io.decode_json, zenoh_io.parse_waypoints

    def decode_json(payload: bytes, limit: int, checkpoint: Callable[[], None]) -> Any:
        calls = [0]

        def counted() -> None:
            calls[0] += 1
            checkpoint()

        data = original_decode(payload, limit, counted)
        seen.append((sys.getprofile(), getattr(checkpoint, "__self__", None), calls[0]))
        return data

    def parse_waypoints(*args: Any) -> Any:
        seen.append((type(sys.getprofile()), None, 0))
        return original_parse(*args)

    monkeypatch.setattr(zenoh_io, "decode_json", decode_json)
    monkeypatch.setattr(zenoh_io, "parse_waypoints", parse_waypoints)
    waypoints = [waypoint_at(0.5 * k) for k in range(1000)]
    message = json.dumps({**TRAJECTORY, "id": "long", "waypoints": waypoints})
    assert len(message) > zenoh_io.DECODE_ON_ARRIVAL_BYTES + JSON_PIECE  # decoded in pieces
    served = Running(StandIn())
    try:
        with served.session() as session:
            session.put(f"{PREFIX}/trajectory", message)
            wait_until(lambda: any(c[0] == "trajectory" for c in served.handler.calls), "it")
    finally:
        served.stop()
    (hook, owner, calls), (parse_hook, _, _) = seen
    assert hook is None and isinstance(owner, zenoh_io._Yielding)
    assert calls > len(waypoints)  # before every waypoint's value at least
    assert parse_hook is zenoh_io._Yielding


def test_the_pause_checkpoint_stops_a_parse_once_the_interface_closes() -> None:
    stop = threading.Event()
    pausing = zenoh_io._Yielding(stop)
    sys.setprofile(pausing)
    try:
        with pausing.unhooked() as checkpoint:
            assert sys.getprofile() is None
            checkpoint()  # within its slice: nothing to do
            stop.set()
            time.sleep(2 * zenoh_io.PARSE_SLICE)
            with pytest.raises(zenoh_io._ParseStopped):
                checkpoint()
            stop.clear()  # the hook is back on below
        assert sys.getprofile() is pausing
    finally:
        sys.setprofile(None)


def test_the_parse_thread_pauses_with_a_short_timer_slack() -> None:
    """Its pauses end within ~PARSE_TIMER_SLACK_NS (Linux: per thread; its default of
    50 us made each 10 us pause ~65 us)."""
    got: list[int] = []

    def set_up_and_read() -> None:
        zenoh_io._set_up_parse_thread()
        got.append(ctypes.CDLL(None).prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0))

    thread = threading.Thread(target=set_up_and_read)
    thread.start()
    thread.join(WAIT)
    assert got == [zenoh_io.PARSE_TIMER_SLACK_NS]
    assert ctypes.CDLL(None).prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0) != got[0]  # this thread's


def test_a_stalled_loop_keeps_queues_bounded_and_busy_replies_immediate() -> None:
    served = Running(StandIn(), queue_depth=4)
    try:
        with served.session() as session:
            publisher = session.declare_publisher(
                f"{PREFIX}/trajectory", congestion_control=zenoh.CongestionControl.BLOCK
            )
            events: list[dict] = []
            session.declare_subscriber(
                f"{PREFIX}/events", lambda s: events.append(json.loads(s.payload.to_bytes()))
            )
            assert ask(session, "cmd/status")["ok"]
            served.handler.calls.clear()
            passes: list[int] = []  # handler calls so far, at each loop pass

            def count_per_pass() -> None:
                passes.append(len(served.handler.calls))
                if passes[-1] < 8:
                    served.loop.call_soon(count_per_pass)

            release = served.block_loop()
            for i in range(10):
                publisher.put(json.dumps({**TRAJECTORY, "id": f"p{i}"}))
            wait_until(lambda: served.interface.stats().get("trajectory_puts") == 10, "10 puts")
            replies: list[dict] = []

            def on_reply(reply: zenoh.Reply) -> None:
                sample = reply.ok if reply.ok is not None else reply.err
                replies.append(json.loads(sample.payload.to_bytes()))

            for _ in range(7):
                session.get(f"{PREFIX}/cmd/status", on_reply, timeout=WAIT)
            wait_until(lambda: len(replies) == 3, "the immediate busy replies")  # loop held
            assert {r["error"]["code"] for r in replies} == {"busy"}
            served.interface.publish_event({"event": "fault", "why": "during the flood"})
            stats = served.interface.stats()
            served.loop.call_soon_threadsafe(count_per_pass)
            release.set()
            wait_until(lambda: len(replies) == 7, "the queued replies")
            wait_until(lambda: len(served.handler.calls) == 8, "the queued work")
            wait_until(lambda: any(e.get("event") == "fault" for e in events), "the fault")
            publisher.undeclare()
    finally:
        served.stop()
    assert stats["trajectories_queue_high_water"] == 4  # never above its depth
    assert stats["trajectories_queue_dropped"] == 6
    assert stats["commands_queue_dropped"] == 3
    # 6 "busy" rejection events: the interface's own use at most half of the event queue,
    # so the service's fault event still found room
    assert stats["events_queue_dropped"] == 4
    assert sum(r["ok"] for r in replies) == 4
    calls = [c[0] for c in served.handler.calls]
    assert calls.count("trajectory") == 4 and calls.count("status") == 4
    # at most one request per queue and loop pass, so two handler calls per pass at most
    assert max(b - a for a, b in itertools.pairwise(passes)) <= 2


def test_undecoded_trajectories_waiting_weigh_at_most_two_of_the_largest() -> None:
    """Large trajectories wait undecoded for the parse thread, each costing work in
    proportion to its size: besides the queue's depth, those waiting weigh at most
    QUEUED_LARGEST_MESSAGES x max_message_bytes, so the last in line waits a bounded
    time.  With the loop held: of five ~20 KB messages (max 32 KiB) three wait (a fourth
    would weigh more than 64 KiB), the others are answered busy at once; a small one,
    decoded on arrival, still finds room by the depth."""
    from daemon.interface.zenoh_io import DECODE_ON_ARRIVAL_BYTES, QUEUED_LARGEST_MESSAGES

    largest = 32 * 1024
    served = Running(StandIn(), queue_depth=8, max_message_bytes=largest)
    padding = " " * 20_000  # JSON whitespace: parses to the same small trajectory
    big = json.dumps(TRAJECTORY) + padding
    assert DECODE_ON_ARRIVAL_BYTES < len(big) < largest
    fits = QUEUED_LARGEST_MESSAGES * largest // len(big)  # 3
    try:
        with served.session() as session:
            assert ask(session, "cmd/status")["ok"]
            served.handler.calls.clear()
            replies: list[dict] = []

            def on_reply(reply: zenoh.Reply) -> None:
                sample = reply.ok if reply.ok is not None else reply.err
                replies.append(json.loads(sample.payload.to_bytes()))

            release = served.block_loop()
            for _ in range(5):
                session.get(f"{PREFIX}/trajectory", on_reply, payload=big, timeout=WAIT)
            wait_until(lambda: len(replies) == 5 - fits, "the busy replies at once")
            assert {r["error"]["code"] for r in replies} == {"busy"}
            session.get(f"{PREFIX}/trajectory", on_reply, payload=json.dumps(TRAJECTORY))

            def decided() -> bool:  # the small one queued or dropped
                counts = served.interface.stats()
                return (
                    counts["trajectories_queue_high_water"] + counts["trajectories_queue_dropped"]
                    == 6
                )

            wait_until(decided, "the small one queued or dropped")
            stats = served.interface.stats()
            release.set()
            wait_until(lambda: len(replies) == 6, "the queued replies")
    finally:
        served.stop()
    assert stats["trajectories_queue_high_water"] == fits + 1  # the small one too
    assert stats["trajectories_queue_dropped"] == 5 - fits
    assert sum(r["ok"] for r in replies) == fits + 1


FLOODER = r"""
import json, sys, time, zenoh

endpoint, prefix, seconds, rate = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
good = json.dumps(json.loads(sys.argv[5])).encode()
bad = b'{"waypoints": [NaN, ' + b"0, " * 2000 + b"0]}"
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/gossip/enabled", "false")
replies = {"ok": 0, "busy": 0, "other": 0}


def on_reply(reply):
    sample = reply.ok if reply.ok is not None else reply.err
    body = json.loads(sample.payload.to_bytes())
    code = "ok" if body.get("ok") else body.get("error", {}).get("code")
    replies[code if code in replies else "other"] += 1


with zenoh.open(conf) as session:
    pub = session.declare_publisher(prefix + "/trajectory")
    sent = queries = 0
    start = time.monotonic()
    while (now := time.monotonic() - start) < seconds:
        while sent < now * rate:
            pub.put(good if sent % 2 else bad)
            sent += 1
            if sent % 10 == 0:
                session.get(prefix + "/cmd/status", on_reply, timeout=5)
                queries += 1
        time.sleep(0.001)
    time.sleep(1.0)
print(json.dumps({"puts": sent, "queries": queries, "seconds": seconds, "replies": replies}))
"""


def test_a_flood_costs_bounded_memory_and_every_query_gets_one_reply(tmp_path: Path) -> None:
    """Thousands of puts per second for 2 s from another process, at a slow handler."""
    handler = StandIn()
    handler.delay = 0.001  # 1 ms per request: the loop cannot keep up with the flood
    served = Running(handler, queue_depth=8, state_rate_hz=100.0)
    lateness: list[float] = []
    stop_timer = threading.Event()

    async def lag_probe() -> None:  # a timer task measuring its own lateness
        period = 0.005
        while not stop_timer.is_set():
            due = served.loop.time() + period
            await asyncio.sleep(period)
            lateness.append(served.loop.time() - due)

    script = tmp_path / "flooder.py"
    script.write_text(FLOODER)
    process = psutil.Process()
    trajectory_json = json.dumps(TRAJECTORY)
    try:
        probe = asyncio.run_coroutine_threadsafe(lag_probe(), served.loop)
        rss_before = process.memory_info().rss
        done = subprocess.run(
            [sys.executable, str(script), served.endpoint, PREFIX, "2.0", "4000", trajectory_json],
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        )
        rss_after = process.memory_info().rss
        stop_timer.set()
        probe.result(WAIT)
        stats = served.interface.stats()
        with served.session() as session:
            assert ask(session, "cmd/status")["ok"]  # still serving
    finally:
        served.stop()
    flood = json.loads(done.stdout)
    lateness.sort()
    figures = {
        "puts": flood["puts"],
        "puts_per_s": flood["puts"] / flood["seconds"],
        "replies": flood["replies"],
        "rss_growth_mb": (rss_after - rss_before) / 2**20,
        "loop_lag_p50_ms": 1e3 * lateness[len(lateness) // 2],
        "loop_lag_p99_ms": 1e3 * lateness[int(0.99 * (len(lateness) - 1))],
        "loop_lag_max_ms": 1e3 * lateness[-1],
        "stats": stats,
    }
    print(json.dumps(figures, indent=1))
    assert flood["puts"] >= 4000
    assert sum(flood["replies"].values()) == flood["queries"]  # one reply each, no silence
    assert flood["replies"]["other"] == 0
    assert flood["replies"]["busy"] > 0 and stats["trajectories_queue_dropped"] > 0
    assert stats["trajectories_queue_high_water"] <= 8
    assert stats["commands_queue_high_water"] <= 8
    assert stats["events_queue_high_water"] <= 8
    assert rss_after - rss_before < 32 * 2**20


# -- (4) configuration ------------------------------------------------------------------------


def scouting(conf: zenoh.Config) -> tuple[bool, bool]:
    data = json.loads(conf.get_json("scouting"))
    return data["multicast"]["enabled"], data["gossip"]["enabled"]


def shared_memory(conf: zenoh.Config) -> bool:
    return json.loads(conf.get_json("transport/shared_memory/enabled"))


def test_default_config_is_loopback_only_without_multicast_or_gossip() -> None:
    conf = build_zenoh_config(validate_section(ZenohSettings, {}, "zenoh"), PREFIX)
    assert scouting(conf) == (False, False)
    # 7448: zenoh routers (rmw_zenohd too) take 7447
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(conf.get_json("connect/endpoints")) == []
    assert json.loads(conf.get_json("mode")) == "peer"
    assert not shared_memory(conf)
    client = client_zenoh_config(["tcp/127.0.0.1:7447"])
    assert scouting(client) == (False, False)
    assert not shared_memory(client)
    assert json.loads(client.get_json("listen/endpoints")) == []


raw_configs = st.fixed_dictionaries(
    {},
    optional={
        "transport": st.just({"link": {"tx": {"lease": 5000}}}),
        "timestamping": st.just({"enabled": True}),
        "queries_default_timeout": st.integers(100, 100000),
    },
)


@given(
    raw=raw_configs,
    mode=st.sampled_from(["peer", "client"]),
    multicast=st.booleans(),
    gossip=st.booleans(),
)
def test_multicast_and_gossip_are_on_only_when_explicitly_allowed(
    raw: dict, mode: str, multicast: bool, gossip: bool
) -> None:
    data = {"mode": mode, "config": raw, "multicast_scouting": multicast, "gossip": gossip}
    data["expose"] = multicast  # multicast scouting needs expose: true
    if mode == "client":
        data["connect"] = ["tcp/127.0.0.1:7447"]
    conf = build_zenoh_config(validate_section(ZenohSettings, data, "zenoh"), PREFIX)
    assert scouting(conf) == (multicast, gossip)


def test_ingress_limits_become_zenoh_downsampling_rules_under_the_prefix() -> None:
    limits = {"trajectory": 5.0, "cmd/*": 20.0}
    settings = validate_section(ZenohSettings, {"ingress_limits_hz": limits}, "zenoh")
    (entry,) = json.loads(build_zenoh_config(settings, PREFIX).get_json("downsampling"))
    assert entry["flows"] == ["ingress"] and set(entry["messages"]) == {"put", "query"}
    rules = {rule["key_expr"]: rule["freq"] for rule in entry["rules"]}
    assert rules == {f"{PREFIX}/trajectory": 5.0, f"{PREFIX}/cmd/*": 20.0}
    default = build_zenoh_config(validate_section(ZenohSettings, {}, "zenoh"), PREFIX)
    assert json.loads(default.get_json("downsampling")) == []


@pytest.mark.parametrize(
    ("limits", "message"),
    [
        ({"/trajectory": 5}, "not a key under the prefix"),
        ({"cmd/**x": 5}, "not a key under the prefix"),
        ({"": 5}, "not a key under the prefix"),
        ({"trajectory": 0}, "greater than 0"),
        ({"trajectory": "fast"}, "valid number"),
    ],
)
def test_bad_ingress_limits_name_the_key(limits: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as caught:
        validate_section(ZenohSettings, {"ingress_limits_hz": limits}, "zenoh")
    assert "ingress_limits_hz" in str(caught.value)


def test_ingress_limits_and_raw_downsampling_are_exclusive() -> None:
    rule = {"key_expr": "a", "freq": 1.0}
    raw = {"downsampling": [{"flows": ["ingress"], "messages": ["put"], "rules": [rule]}]}
    with pytest.raises(ConfigError, match="use one of them"):
        validate_section(
            ZenohSettings, {"ingress_limits_hz": {"trajectory": 1.0}, "config": raw}, "zenoh"
        )


def test_zenoh_drops_what_comes_faster_than_the_ingress_limit() -> None:
    """With trajectory limited to 2 Hz, a burst of ten puts reaches the daemon as one,
    unlimited keys are served as usual, and a put half a second later is let through."""
    served = Running(StandIn(), ingress_limits_hz={"trajectory": 2.0})
    try:
        counts = served.interface.stats
        with served.session() as session:
            assert ask(session, "cmd/status")["ok"]
            for _ in range(10):
                session.put(f"{PREFIX}/trajectory", b"not json")
            wait_until(lambda: counts().get("trajectory_puts", 0) >= 1, "the first put")
            time.sleep(0.3)
            assert counts()["trajectory_puts"] == 1
            assert ask(session, "cmd/status")["ok"]  # another key: not limited
            time.sleep(0.3)
            session.put(f"{PREFIX}/trajectory", b"not json")
            wait_until(lambda: counts()["trajectory_puts"] == 2, "the put after 0.6 s")
    finally:
        served.stop()


@pytest.mark.parametrize(
    "raw",
    [
        {"scouting": {"multicast": {"enabled": True}}},
        {"scouting/gossip/enabled": True},
        {"listen": {"endpoints": ["tcp/0.0.0.0:7447"]}},
        {"/connect/endpoints": ["tcp/10.0.0.1:7447"]},
        {"transport": {"shared_memory": {"enabled": True}}},
    ],
)
def test_the_raw_config_cannot_bypass_the_typed_keys(raw: dict) -> None:
    with pytest.raises(ConfigError, match=r"not inside zenoh\.config"):
        validate_section(ZenohSettings, {"config": raw}, "zenoh")


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/0.0.0.0:7447",
        "tcp/[::]:7447",
        "tcp/192.168.1.20:7447",
        "tls/10.0.0.2:7447",
        "tcp/robot.lab:7447",
        "quic/172.16.0.1:7447#iface=eth0",
    ],
)
def test_endpoints_off_loopback_need_expose(endpoint: str) -> None:
    assert not is_local(endpoint)
    for key in ("listen", "connect"):
        with pytest.raises(ConfigError, match=r"set zenoh\.expose: true") as info:
            validate_section(ZenohSettings, {key: [endpoint]}, "zenoh")
        assert endpoint in str(info.value) and "TLS and access control" in str(info.value)
        validate_section(ZenohSettings, {key: [endpoint], "expose": True}, "zenoh")


@pytest.mark.parametrize(
    "endpoint",
    ["tcp/127.0.0.1:7447", "tcp/127.0.0.2:1", "tcp/[::1]:7447", "tcp/localhost:7447",
     "tls/127.0.0.1:7448", "unixsock-stream//run/cdprd.sock"],
)  # fmt: skip
def test_loopback_endpoints_need_no_expose(endpoint: str) -> None:
    assert is_local(endpoint)
    validate_section(ZenohSettings, {"listen": [endpoint]}, "zenoh")


@pytest.mark.parametrize(
    ("data", "words"),
    [
        ({"listen": ["serial/dev/ttyUSB0"]}, "protocol 'serial' is not one of"),
        ({"listen": ["tcp/127.0.0.1"]}, "not of the form tcp/<host>:<port>"),
        ({"mode": "client"}, "needs zenoh.connect"),
        ({"mode": "client", "connect": ["tcp/127.0.0.1:7447"], "listen": []}, None),
        ({"mode": "router"}, "mode"),
        ({"multicast_scouting": True}, "set zenoh.expose: true as well"),
        ({"prefix": "cdpr/*"}, "no wildcards"),
        ({"prefix": "/cdpr/a"}, "no leading or trailing"),
        ({"state_rate_hz": 0}, "state_rate_hz"),
        ({"queue_depth": 0}, "queue_depth"),
        ({"colour": "red"}, "colour"),
        ({"config": {"transport": {"link": {"tls": {"certificate": "x"}}}}}, "unknown field"),
    ],
)
def test_bad_settings_name_the_problem(data: dict, words: str | None) -> None:
    if words is None:
        validate_section(ZenohSettings, data, "zenoh")
        return
    with pytest.raises(ConfigError, match=words.replace("*", r"\*").replace(".", r"\.")):
        validate_section(ZenohSettings, data, "zenoh")


def test_prefix_defaults_to_the_robot_name() -> None:
    assert ZenohSettings().key_prefix("reference8") == "cdpr/reference8"
    assert ZenohSettings(prefix="lab/a").key_prefix("reference8") == "lab/a"


# -- (5) the CLI client ----------------------------------------------------------------------


def cli(served: Running | None, *argv: str, connect: str | None = None) -> int:
    endpoint = connect or (served.endpoint if served else f"tcp/127.0.0.1:{free_port()}")
    return main([*argv, "--connect", endpoint, "--timeout", "2"])


def test_cli_exit_codes_against_a_stand_in_daemon(
    running: Running, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    handler = running.handler
    assert cli(running, "status", "--prefix", PREFIX, "--json") == 0
    assert json.loads(capsys.readouterr().out)["state"] == "IDLE"
    assert cli(running, "status") == 0  # the only daemon alive: found without --prefix
    assert cli(running, "enable") == 1
    assert "enable: refused (invalid_state): cannot enable while BRAKED" in capsys.readouterr().err
    handler.refuse_enable = False
    assert cli(running, "enable") == 0
    assert cli(running, "brake", "--reason", "operator stop", "--client", "ops desk") == 0
    assert cli(running, "goto", "0.1", "-0.2", "1.2") == 0
    c = math.sqrt(0.5)
    assert cli(running, "goto", "0", "0", "1", str(c), "0", "0", str(c), "--preempt") == 0
    assert [call[0] for call in handler.calls[-5:]] == ["enable", "enable", "brake", "goto", "goto"]
    assert handler.calls[-3][1] == {"reason": "operator stop", "client": "ops desk"}
    assert handler.calls[-2][1]["pose"] == Pose((0.1, -0.2, 1.2))
    # who asks: user@host:pid unless --client says otherwise; --preempt only if given
    assert handler.calls[-2][1]["client"].endswith(f":{os.getpid()}")
    assert "preempt" not in handler.calls[-2][1] and handler.calls[-1][1]["preempt"] is True
    for argv in (["goto", "1", "2"], ["goto", "1", "2", "x"], ["goto", "0", "0", "nan"]):
        calls = len(handler.calls)
        assert cli(running, *argv) == 2, argv
        assert len(handler.calls) == calls
    assert "3 or 7 numbers" in capsys.readouterr().err

    good = tmp_path / "good.yaml"
    good.write_text(
        "waypoints:\n"
        "  - {t: 0, position: [0, 0, 1.25], quaternion: {w: 1, x: 0, y: 0, z: 0}}\n"
        "  - {t: 3, position: [0, 0, 1.30], quaternion: {w: 1, x: 0, y: 0, z: 0}}\n"
    )
    capsys.readouterr()
    assert cli(running, "send", str(good), "--id", "cli-1", "--json") == 0
    out = json.loads(capsys.readouterr().out)
    assert out["id"] == "cli-1" and out["result"] == {"duration": 3.0}
    backwards = tmp_path / "backwards.json"
    waypoints = TRAJECTORY["waypoints"]
    backwards.write_text(json.dumps({"waypoints": [waypoints[1], waypoints[0]]}))
    assert cli(running, "send", str(backwards)) == 1
    assert "send: refused (rejected)" in capsys.readouterr().err
    too_long = tmp_path / "long.json"
    too_long.write_text(json.dumps({"waypoints": [waypoints[0], {**waypoints[1], "t": 500}]}))
    assert cli(running, "send", str(too_long)) == 1  # the handler's own rejection
    assert '"limit": "max_duration"' in capsys.readouterr().err
    calls = len(handler.calls)
    assert cli(running, "send", str(tmp_path / "missing.yaml")) == 2
    (tmp_path / "nan.yaml").write_text("waypoints: [.nan]\n")
    assert cli(running, "send", str(tmp_path / "nan.yaml")) == 2
    (tmp_path / "list.json").write_text("[1, 2]")
    assert cli(running, "send", str(tmp_path / "list.json")) == 2
    assert cli(running, "send", str(good), "--start", "soon") == 2
    assert len(handler.calls) == calls
    err = capsys.readouterr().err
    assert "missing.yaml: cannot read" in err and "not strict JSON" in err
    assert cli(running, "status", "--prefix", "cdpr/nobody") == 3  # wrong prefix: no answer
    assert "no daemon answered on cdpr/nobody/cmd/status" in capsys.readouterr().err


def test_cli_without_a_daemon_exits_3_quickly(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["status"], ["status", "--prefix", PREFIX], ["enable", "--prefix", PREFIX]):
        assert cli(None, *argv) == 3
        assert "no daemon reachable" in capsys.readouterr().err


def test_client_reports_the_rejection_reason(running: Running) -> None:
    waypoints = TRAJECTORY["waypoints"]
    with CdprClient(PREFIX, running.endpoint, timeout=WAIT) as client:
        assert client.alive()
        accepted = client.send_trajectory(parse_trajectory(TRAJECTORY), request_id="obj")
        assert accepted["result"] == {"duration": 2.0} and accepted["id"] == "obj"
        assert client.send_trajectory(TRAJECTORY)["id"]  # an id is made up when none is given
        with pytest.raises(RequestError) as info:
            client.send_trajectory({"waypoints": [waypoints[0], {**waypoints[1], "t": -1.0}]})
        assert info.value.code == "rejected" and "times" in info.value.reason
        states: list[dict] = []
        sub = client.subscribe_state(states.append)
        wait_until(lambda: len(states) >= 2, "two states")
        sub.undeclare()


class Escaping(StandIn):
    """A handler from which a TrajectoryError escapes, at once (goto), from an awaited
    reply (hold) and from an awaited verdict (trajectory): as when planning outside the
    service's own try blocks breaks a limit."""

    def command(self, name: str, args: dict[str, Any]) -> Any:
        if name == "goto":
            raise TrajectoryError("linear_speed", "1.5 m/s above 1 m/s", waypoint=0, value=1.5)
        if name == "hold":

            async def plan() -> dict[str, Any]:
                raise TrajectoryError("max_duration", "the stop would last 9e+99 s")

            return plan()
        return super().command(name, args)

    def submit_trajectory(self, trajectory: Trajectory, start: float | None, claim: Any) -> Any:
        async def validate() -> dict[str, Any]:
            raise TrajectoryError("cable_length", "cable 3 at 4.5 m", waypoint=1, value=4.5)

        return validate()


def test_a_trajectory_error_from_the_handler_is_a_rejection_not_internal() -> None:
    served = Running(Escaping())
    session = served.session()
    try:
        goto = ask(session, "cmd/goto", json.dumps({"position": [0.1, 0.0, 1.3]}))
        hold = ask(session, "cmd/hold")
        trajectory = ask(session, "trajectory", json.dumps(TRAJECTORY))
    finally:
        session.close()
        served.stop()
    assert goto["error"] == {
        "code": "rejected",
        "reason": "goto rejected: waypoint 0: linear_speed: 1.5 m/s above 1 m/s",
        "limit": "linear_speed",
        "waypoint": 0,
        "value": 1.5,
    }
    assert hold["error"]["code"] == "rejected" and hold["error"]["limit"] == "max_duration"
    assert trajectory["error"]["code"] == "rejected"
    assert (trajectory["error"]["limit"], trajectory["error"]["waypoint"]) == ("cable_length", 1)


BIG_PUTS = r"""
import json, sys, zenoh

conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as session:
    for _ in range(10):  # above zenoh's 3 KiB shared-memory threshold
        session.put(sys.argv[2] + "/trajectory", b'{"waypoints": "' + b"x" * 6000 + b'"}')
    list(session.get(sys.argv[2] + "/cmd/status", timeout=10))
"""


def test_local_senders_of_large_messages_do_not_grow_memory(
    running: Running, tmp_path: Path
) -> None:
    """zenoh's shared-memory transport kept ~20 MB per such sender: it is off."""
    script = tmp_path / "big_puts.py"
    script.write_text(BIG_PUTS)
    process = psutil.Process()
    growth = []
    for _ in range(4):
        before = process.memory_info().rss
        subprocess.run(
            [sys.executable, str(script), running.endpoint, PREFIX], timeout=60, check=True
        )
        growth.append(process.memory_info().rss - before)
    print("RSS growth per sender (MB):", [round(g / 2**20, 2) for g in growth])
    assert sum(growth) < 16 * 2**20


# -- exposing the daemon: the configurations of docs/reference/zenoh-api.md, on loopback ----

DOCS = Path(__file__).resolve().parents[2] / "docs" / "reference" / "zenoh-api.md"
IDENTITIES = ("cdprd", "router", "planner", "monitor", "intruder")


def docs_block(name: str) -> str:
    """The fenced code block after `<!-- tested: name -->` in docs/reference/zenoh-api.md."""
    after = DOCS.read_text(encoding="utf-8").split(f"<!-- tested: {name} -->", 1)[1]
    return after.split("```", 2)[1].split("\n", 1)[1]


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA and one certificate per identity (CN = its name), made with openssl."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    folder = tmp_path_factory.mktemp("tls")

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
            "-subj", "/CN=test CA")  # fmt: skip
    for name in IDENTITIES:
        (folder / f"{name}.ext").write_text(
            "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n"
        )
        openssl("req", *ec, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-out", f"{name}.pem", "-days", "2",
                "-extfile", f"{name}.ext")  # fmt: skip
    return folder


def tls(folder: Path, name: str) -> dict:
    """The raw zenoh config of a client with certificate `name`."""
    return {
        "transport": {
            "link": {
                "tls": {
                    "root_ca_certificate": str(folder / "ca.pem"),
                    "connect_certificate": str(folder / f"{name}.pem"),
                    "connect_private_key": str(folder / f"{name}.key"),
                    "enable_mtls": True,
                }
            }
        }
    }


def sees_state(client: CdprClient, expected: bool) -> bool:
    """Whether state messages reach the client (waits for them when `expected`)."""
    states: list[dict] = []
    sub = client.subscribe_state(states.append)
    if expected:
        wait_until(lambda: len(states) >= 2, "state messages")
    else:
        time.sleep(0.3)
    sub.undeclare()
    return bool(states)


def check_access(folder: Path, endpoint: str, prefix: str, handler: StandIn) -> None:
    """The planner commands and watches, the monitor only watches, others see nothing."""
    with CdprClient(prefix, endpoint, timeout=WAIT, zenoh_config=tls(folder, "planner")) as c:
        assert c.alive()
        assert c.status()["state"] == "IDLE"
        assert c.send_trajectory(TRAJECTORY)["result"]["duration"] == 2.0
        assert sees_state(c, expected=True)
    for name in ("monitor", "intruder"):
        watcher = name == "monitor"
        with CdprClient(prefix, endpoint, timeout=0.5, zenoh_config=tls(folder, name)) as c:
            assert c.alive() is watcher
            with pytest.raises(UnreachableError):
                c.status()
            with pytest.raises(UnreachableError):
                c.send_trajectory(TRAJECTORY)
            assert sees_state(c, expected=watcher) is watcher
    assert [call[0] for call in handler.calls] == ["status", "trajectory"]


def test_an_exposed_daemon_obeys_only_the_planner_certificate(certificates: Path) -> None:
    block = docs_block("exposed-daemon").replace("/etc/cdprd/tls", str(certificates))
    section = yaml.safe_load(block)["zenoh"]
    endpoint = f"tls/127.0.0.1:{free_port()}"
    assert section["listen"] == ["tls/0.0.0.0:7448"] and section["expose"] is True
    section["listen"] = [endpoint]  # tests stay on loopback
    settings = validate_section(ZenohSettings, section, "zenoh")
    served = Running(StandIn(), settings, prefix=section["prefix"])
    try:
        check_access(certificates, endpoint, section["prefix"], served.handler)
        with pytest.raises(UnreachableError):  # no TLS, no session
            CdprClient(section["prefix"], endpoint.replace("tls/", "tcp/"), timeout=0.5)
    finally:
        served.stop()


def test_several_daemons_behind_a_router_with_access_control(
    certificates: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    local, network = free_port(), free_port()
    router_conf = (
        docs_block("router")
        .replace("/etc/zenoh/tls", str(certificates))
        .replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{local}")
        .replace("tls/0.0.0.0:7448", f"tls/127.0.0.1:{network}")
    )
    daemon_section = yaml.safe_load(docs_block("daemon-behind-router"))["zenoh"]
    assert daemon_section["connect"] == ["tcp/127.0.0.1:7447"]
    daemon_section["connect"] = [f"tcp/127.0.0.1:{local}"]
    settings = validate_section(ZenohSettings, daemon_section, "zenoh")
    endpoint = f"tls/127.0.0.1:{network}"
    router = zenoh.open(zenoh.Config.from_json5(router_conf))
    robots = {name: Running(StandIn(), settings, prefix=f"cdpr/{name}") for name in ("a", "b")}
    try:
        # each daemon's session reaches the router in its own time (seconds on a loaded
        # host): the client below is to find both, so wait until a planner sees both
        planner = zenoh.open(client_zenoh_config([endpoint], tls(certificates, "planner")))
        try:
            both = ["cdpr/a/alive", "cdpr/b/alive"]
            wait_until(lambda: alive_tokens(planner) == both, "both daemons")
        finally:
            planner.close()
        with pytest.raises(ClientError, match="several daemons answer: cdpr/a, cdpr/b"):
            CdprClient(None, endpoint, timeout=WAIT, zenoh_config=tls(certificates, "planner"))
        with pytest.raises(UnreachableError, match="no daemon answers"):
            CdprClient(None, endpoint, timeout=0.5, zenoh_config=tls(certificates, "intruder"))
        for name, served in robots.items():
            check_access(certificates, endpoint, f"cdpr/{name}", served.handler)
        planner = tmp_path / "planner.yaml"
        planner.write_text(yaml.safe_dump(tls(certificates, "planner")))
        argv = ["status", "--prefix", "cdpr/b", "--connect", endpoint, "--timeout", "5", "--json"]
        assert main([*argv, "--zenoh-config", str(planner)]) == 0
        assert json.loads(capsys.readouterr().out)["state"] == "IDLE"
    finally:
        for served in robots.values():
            served.stop()
        router.close()


# -- on one host: only the daemon speaks for the robot (config/hardware-template.yaml) ---

TEMPLATE = Path(__file__).resolve().parents[2] / "config" / "hardware-template.yaml"
FORGED = b'{"version": 1, "forged": true}'


def template_zenoh(access_control: bool) -> ZenohSettings:
    """The hardware template's zenoh section on a free loopback port, with its access
    control or without it."""
    section = load_yaml(TEMPLATE)["zenoh"]
    section["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    if not access_control:
        del section["config"]["access_control"]
    return validate_section(ZenohSettings, section, str(TEMPLATE), "zenoh")


def test_the_templates_access_control_is_the_documented_one() -> None:
    documented = yaml.safe_load(docs_block("only-the-daemon-speaks"))["zenoh"]["config"]
    assert load_yaml(TEMPLATE)["zenoh"]["config"] == documented


@pytest.mark.parametrize("access_control", [True, False])
def test_with_the_templates_zenoh_section_only_the_daemon_speaks(access_control: bool) -> None:
    """Another local process publishes state and events, holds an alive token of a daemon
    that is not there and answers commands under the prefix.  With the template's zenoh
    section none of it reaches a planner; without its access control (the control case)
    it does."""
    served = Running(StandIn(), template_zenoh(access_control))
    forger, planner = served.session(), served.session()
    seen: list[tuple[str, bytes]] = []
    declared: list[Any] = []  # kept: zenoh undeclares what is dropped
    try:
        declared += [
            planner.declare_subscriber(
                f"{PREFIX}/**", lambda s: seen.append((str(s.key_expr), s.payload.to_bytes()))
            ),
            forger.declare_queryable(f"{PREFIX}/cmd/**", lambda q: q.reply(q.key_expr, FORGED)),
            forger.liveliness().declare_token("cdpr/ghost/alive"),
        ]
        wait_until(lambda: len(seen) >= 1, "the daemon's state")
        for key in ("state", "events"):
            forger.put(f"{PREFIX}/{key}", FORGED)
        list(forger.get(f"{PREFIX}/trajectory", timeout=WAIT))  # after the puts, on one link

        forged = {f"{PREFIX}/state", f"{PREFIX}/events"}
        if not access_control:
            wait_until(lambda: {k for k, p in seen if p == FORGED} == forged, "the forged puts")
            wait_until(lambda: "cdpr/ghost/alive" in alive_tokens(planner), "the forged token")
            return
        states = len(seen)
        wait_until(lambda: len(seen) >= states + 3, "three more states")  # forged ones came by
        status = ask(planner, "cmd/status")
        tokens = alive_tokens(planner)
    finally:
        declared.clear()
        forger.close()
        planner.close()
        served.stop()
    assert FORGED not in {payload for _, payload in seen}
    assert status["ok"] and status["result"]["command"] == "status"  # the daemon answered
    assert tokens == [f"{PREFIX}/alive"]
