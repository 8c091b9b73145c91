"""`cdprd run --sim --view` as its own process: a Foxglove WebSocket client written from
the published protocol (tests/foxglove_client.py) connects on loopback, sees the
channels advertised with Foxglove's standard schema names, and decodes the scene, the
transforms and the pose, whose values are the state published over zenoh; the run's
telemetry MCAP reads back with the mcap library with the same standard channels beside
the cycle records.  A view port in use stops the start-up with one line."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect as ws_connect

from daemon.cli import main
from daemon.process.recording import CYCLE_SCHEMA_NAME, CYCLE_TOPIC
from daemon.process.view_gate import refusal
from tests.foxglove_client import SUBPROTOCOLS, collect
from tests.loopback import free_port
from tests.processes import ROOT, connect, finish, stop_impatiently, wait_status

CONFIG = ROOT / "config" / "reference8-cia402.yaml"
TARGET = (0.05, -0.03, 1.28)  # m, away from home (0, 0, 1.25)
STANDARD = {
    "/tf": "foxglove.FrameTransforms",
    "/cdpr/scene": "foxglove.SceneUpdate",
    "/cdpr/pose": "foxglove.PoseInFrame",
    "/cdpr/reference_pose": "foxglove.PoseInFrame",
    "/cdpr/log": "foxglove.Log",
    "/cdpr/series": "cdprd.Series",
    "/cdpr/workspace": "foxglove.SceneUpdate",
}


def _config(tmp_path: Path, zenoh: int, recording: dict | None = None) -> Path:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{zenoh}"]
    data["recording"] = recording or {}
    data["state_dir"] = str(tmp_path / "state")
    data["workspace"] = {"step": 0.2, "tilt": 0.2, "interference": False}  # coarse: quick
    data["environment"] = {
        "boxes": [{"name": "table", "min": [-0.3, 1.0, 0], "max": [0.3, 1.4, 0.5]}]
    }
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _run(config: Path, view: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "daemon.cli", "run", "--sim", "--config", str(config)]
    return subprocess.Popen(
        [*command, "--view", view],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _xyz(v) -> list[float]:
    return [v.x, v.y, v.z]


@pytest.mark.slow  # the daemon as a process
@pytest.mark.timeout(120)
def test_a_foxglove_client_sees_the_robot_as_zenoh_does_and_the_mcap_matches(
    tmp_path: Path,
) -> None:
    zenoh, view = free_port(), free_port()
    (tmp_path / "rec").mkdir()
    config = _config(tmp_path, zenoh, {"telemetry": "rec/cycle.mcap"})
    assert main(["workspace", "--config", str(config)]) == 0  # the map the view shows
    proc = _run(config, f"127.0.0.1:{view}")
    try:
        with connect(zenoh, proc) as client:
            wait_status(client, "idle", 10.0)
            client.enable()
            wait_status(client, "hold", 5.0)
            client.goto(TARGET)
            end = time.monotonic() + 10.0
            while True:  # at the target, holding
                state = client.status()
                assert time.monotonic() < end, f"never held at {TARGET}: {state}"
                if state["state"] == "hold" and _zenoh_state(client)["pose"]["position"][0] > 0.04:
                    break
                time.sleep(0.1)
            time.sleep(1.0)  # settled: the view's pose and zenoh's come from different cycles
            cyclic = set(STANDARD) - {"/cdpr/log"}  # a log message only when something happens
            subprotocol, channels, first = collect(f"ws://127.0.0.1:{view}", cyclic)
            published = _zenoh_state(client)
    finally:
        stop_impatiently(proc)
        out = finish(proc, terminate=False)
    assert proc.returncode == 0, out

    assert subprotocol in ("foxglove.sdk.v1", "foxglove.websocket.v1")
    assert {topic: c["schemaName"] for topic, c in channels.items()} == STANDARD
    assert {c["encoding"] for t, c in channels.items() if t != "/cdpr/series"} == {"protobuf"}

    zenoh_position = np.array(published["pose"]["position"])
    q = published["pose"]["quaternion"]
    assert np.allclose(zenoh_position, TARGET, atol=5e-3)
    pose = first["/cdpr/pose"].message.pose
    assert np.allclose(_xyz(pose.position), zenoh_position, atol=1e-4)
    o = pose.orientation
    # the angle between the two (different cycles of a hold: CI saw 2.5e-4 rad on a loaded
    # host); a wrong frame or component order would be off by far more
    dot = abs(np.dot([o.w, o.x, o.y, o.z], [q["w"], q["x"], q["y"], q["z"]]))
    assert 2.0 * np.arccos(min(dot, 1.0)) < 1e-3
    platform = {t.child_frame_id: t for t in first["/tf"].message.transforms}["platform"]
    assert np.allclose(_xyz(platform.translation), zenoh_position, atol=1e-4)
    scene = {e.id: e for e in first["/cdpr/scene"].message.entities}
    (box,) = scene["platform"].cubes
    assert np.allclose(_xyz(box.pose.position), zenoh_position, atol=0.05)  # box centre
    assert len(scene["cables"].lines) == 8
    assert first["/cdpr/series"].message["tensions"][0] > 0
    # the saved map's boundary at home, the environment's table, the box
    workspace = {e.id: e for e in first["/cdpr/workspace"].message.entities}
    assert len(workspace["workspace"].cubes) > 50
    (table,) = workspace["environment"].cubes
    assert np.allclose(_xyz(table.pose.position), [0.0, 1.2, 0.25])

    recording = next((tmp_path / "rec").glob("cycle-*.mcap"))
    with recording.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        names = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        counts = summary.statistics.channel_message_counts
        by_topic = {c.topic: counts.get(c.id, 0) for c in summary.channels.values()}
        poses = [
            _xyz(m.transforms[0].translation)
            for _s, _c, _m, m in reader.iter_decoded_messages(topics=["/tf"])
        ]
    assert names == {**STANDARD, CYCLE_TOPIC: CYCLE_SCHEMA_NAME}
    # every cycle recorded, the scene at view.rate_hz (30 Hz) of a 500 Hz cycle
    assert by_topic["/tf"] == by_topic["/cdpr/scene"] > 10
    assert by_topic[CYCLE_TOPIC] > 10 * by_topic["/tf"]
    assert by_topic["/cdpr/log"] >= 3  # idle, enabled, goto, ...
    assert by_topic["/cdpr/workspace"] == 1  # recorded once
    assert min(np.linalg.norm(np.subtract(p, TARGET)) for p in poses) < 5e-3


def _zenoh_state(client) -> dict:
    """The next state the daemon publishes over zenoh."""
    got: list[dict] = []
    arrived = threading.Event()

    def on_state(state: dict) -> None:
        if "pose" in state and not got:
            got.append(state)
            arrived.set()

    subscriber = client.subscribe_state(on_state)
    try:
        assert arrived.wait(5.0), "no state over zenoh"
    finally:
        subscriber.undeclare()
    return got[0]


def _upgrade(port: int, host: str = "127.0.0.1", origin: str | None = None) -> int | str:
    """One WebSocket upgrade to the view at 127.0.0.1:`port`, with `host` in the Host
    header (as a page at http://`host`:`port` that resolves to 127.0.0.1 sends it) and
    `origin`: the first message's op if the server let it in, else the HTTP status."""
    headers = None if origin is None else {"Origin": origin}
    end = time.monotonic() + 30.0
    while True:
        try:
            sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
            break
        except OSError:  # the companion is still starting
            assert time.monotonic() < end, f"no view on port {port}"
            time.sleep(0.1)
    try:
        with ws_connect(
            f"ws://{host}:{port}",
            sock=sock,
            subprotocols=SUBPROTOCOLS,
            additional_headers=headers,
            open_timeout=10.0,
        ) as ws:
            return json.loads(ws.recv(timeout=10.0))["op"]
    except InvalidStatus as exc:
        return exc.response.status_code


@pytest.mark.slow  # the daemon as a process
@pytest.mark.timeout(120)
def test_the_view_lets_in_no_origin_and_foxglove_but_not_other_pages_or_rebound_hosts(
    tmp_path: Path,
) -> None:
    """Browsers send Origin on every WebSocket: a page of another site (evil.example), or
    one whose name was rebound to 127.0.0.1 (Host and Origin evil.example), is refused
    with 403 before any protocol message; Foxglove's web app and clients that send no
    Origin get the server's serverInfo."""
    view = free_port()
    proc = _run(_config(tmp_path, free_port()), f"127.0.0.1:{view}")
    rebound = f"evil.example:{view}"
    try:
        outcomes = {
            "no origin": _upgrade(view),
            "localhost": _upgrade(view, host="localhost"),
            "foxglove": _upgrade(view, origin="https://app.foxglove.dev"),
            "evil origin": _upgrade(view, origin="http://evil.example"),
            "rebound": _upgrade(view, host="evil.example", origin=f"http://{rebound}"),
            "rebound host": _upgrade(view, host="evil.example"),
            "null origin": _upgrade(view, origin="null"),
        }
    finally:
        out = finish(proc)
    assert outcomes == {
        "no origin": "serverInfo",
        "localhost": "serverInfo",
        "foxglove": "serverInfo",
        "evil origin": 403,
        "rebound": 403,
        "rebound host": 403,
        "null origin": 403,
    }, out
    assert "live view: refused a connection: Origin 'http://evil.example' is not in" in out
    assert f"live view: refused a connection: Host '{rebound}' is not this view's" in out


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
@pytest.mark.timeout(120)
def test_run_with_its_view_port_taken_exits_with_one_line(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", free_port()))
        taken.listen()
        port = taken.getsockname()[1]
        config = _config(tmp_path, free_port())
        proc = _run(config, str(port))
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    lines = [line for line in out.splitlines() if " INFO " not in line]
    assert len(lines) == 1, out
    assert lines[0].startswith(f"error: {config}: view: cannot serve on 127.0.0.1:{port}: ")
    assert "Address already in use" in lines[0]


@pytest.mark.parametrize(
    ("fields", "refused"),
    [
        ([("host", "127.0.0.1:8765")], None),
        ([("host", "LOCALHOST.:8765"), ("origin", "https://app.foxglove.dev")], None),
        ([("host", "[::1]:8765")], "Host '[::1]:8765' is not this view's address"),
        ([("host", "evil.example")], "Host 'evil.example' is not this view's address"),
        ([("host", "127.0.0.1.evil.example:8765")], "is not this view's address"),
        ([("origin", "https://app.foxglove.dev")], "0 Host and 1 Origin headers"),
        ([("host", "127.0.0.1"), ("host", "evil.example")], "2 Host and 0 Origin headers"),
        (
            [("host", "127.0.0.1"), ("origin", "https://app.foxglove.dev"), ("origin", "null")],
            "1 Host and 2 Origin headers",
        ),
        (
            [("host", "127.0.0.1"), ("origin", "https://app.foxglove.dev.evil.example")],
            "Origin 'https://app.foxglove.dev.evil.example' is not in view.allowed_origins",
        ),
    ],
)
def test_the_gate_reads_host_and_origin_strictly(
    fields: list[tuple[str, str]], refused: str | None
) -> None:
    why = refusal(fields, ("https://app.foxglove.dev",), ("127.0.0.1", "localhost"))
    assert why == refused if refused is None else refused in (why or "")
