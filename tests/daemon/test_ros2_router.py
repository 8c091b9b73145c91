"""Beside a ROS 2 graph's zenoh router on 7447 (tests.stand_in_router, set up as rmw_zenohd
is), `cdprd run --sim` with a shipped config and the one line docs/guide/ros2.md gives
starts, and a ROS 2 node that reaches the router only (rmw_zenoh's session connects to
tcp/localhost:7447) drives it: enable by service, a Path flown, a goal of the fly_path
action with feedback cancelled midway (the robot holds), brake by service.  The
client is written from rmw_zenoh's design (tests/daemon/test_ros2_process.py and
test_ros2_services.py), not from the project's encoder.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from tests.daemon.test_ros2_action import (
    CANCELED,
    ERROR_NONE,
    FEEDBACK,
    Client,
    decode,
    new_id,
)
from tests.daemon.test_ros2_action import path as action_path
from tests.daemon.test_ros2_process import (
    PATH,
    POSE,
    STATUS,
    Inbox,
    _listening,
    key,
    path,
    wait,
)
from tests.daemon.test_ros2_services import request_attachment, service_key, trigger
from tests.loopback import zenoh_peer
from tests.processes import CONFIG, ROOT, finish, start_daemon

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]

ROUTER_PORT = 7447  # rmw_zenohd's
DAEMON_PORT = 7448  # the shipped configs'
GUIDE = ROOT / "docs" / "guide" / "ros2.md"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"


def guide_line() -> dict:
    """The guide's one-line `ros2:` section that joins a ROS 2 graph."""
    (line,) = [x for x in GUIDE.read_text().splitlines() if x.startswith("ros2: {enabled: true")]
    return yaml.safe_load(line)


def test_the_guide_line_connects_to_rmw_zenohds_port() -> None:
    assert guide_line() == {"ros2": {"enabled": True, "router": "tcp/127.0.0.1:7447"}}


def test_beside_a_router_on_7447_the_shipped_config_is_driven_from_ros2(tmp_path: Path) -> None:
    """The daemon first, the graph's router later (the bridge waits for it, the daemon
    runs meanwhile), then a ROS 2 node on the router drives the robot; the router
    restarts, and a node on the new one resets the robot."""
    for port, whose in ((ROUTER_PORT, "the stand-in router"), (DAEMON_PORT, "the daemon")):
        if _listening(port):
            pytest.skip(
                f"port {port} is taken on this host (a real router or daemon?): {whose} uses it"
            )
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data.update(guide_line())
    config = tmp_path / "cdprd.yaml"
    config.write_text(yaml.safe_dump(data))
    proc = start_daemon(config, "--sim", log=tmp_path / "daemon.log")
    router = None
    try:
        wait(lambda: _listening(DAEMON_PORT), 60.0, "the daemon to listen")
        router = start_router()
        ros_node = zenoh_peer(ROUTER_PORT)  # reaches the daemon through the router only
        try:
            _drive(ros_node)
        finally:
            ros_node.close()
        stop_router(router)  # the graph's router restarts: the node is back on it
        router = start_router()
        ros_node = zenoh_peer(ROUTER_PORT)
        try:
            diagnostics = Inbox(ros_node, "/diagnostics", DIAGNOSTICS, domain=0)
            wait(lambda: _state(diagnostics) == "braked", 30.0, "the node back on the router")
            reset = trigger(ros_node, service_key("/reset"), 1)
            assert reset.success, reset.message
            wait(lambda: _state(diagnostics) == "idle", 10.0, "idle after the reset")
        finally:
            ros_node.close()
    finally:
        finish(proc)
        if router is not None:
            stop_router(router)
    log = (tmp_path / "daemon.log").read_text()
    assert proc.returncode == 0, log
    assert "ROS 2: the router does not answer" in log and "ROS 2: the router answers now" in log


def start_router() -> subprocess.Popen:
    router = subprocess.Popen(
        [sys.executable, "-m", "tests.stand_in_router", f"tcp/127.0.0.1:{ROUTER_PORT}"],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    assert router.stdout is not None and router.stdout.readline().strip() == b"ready"
    return router


def stop_router(router: subprocess.Popen) -> None:
    assert router.stdin is not None
    router.stdin.close()
    router.wait(timeout=10)


def _state(diagnostics: Inbox) -> str | None:
    """The safety state the last DiagnosticArray reports."""
    msg, _ = diagnostics.last()
    if msg is None:
        return None
    (status,) = msg.status
    return {v.key: v.value for v in status.values}["state"]


def _drive(s: zenoh.Session) -> None:
    diagnostics = Inbox(s, "/diagnostics", DIAGNOSTICS, domain=0)
    poses = Inbox(s, "/pose", POSE, domain=0)
    verdicts = Inbox(s, "/trajectory_status", STATUS, domain=0)
    wait(lambda: _state(diagnostics) == "idle", 90.0, "the daemon idle, seen through the router")
    tokens = [str(r.ok.key_expr) for r in s.liveliness().get("@ros2_lv/0/**", timeout=5.0)]
    assert any(t.split("/")[5:] == ["NN", "%", "%", "cdprd"] for t in tokens), tokens

    enabled = trigger(s, service_key("/enable"), 1)
    assert enabled.success, enabled.message
    wait(lambda: poses.count() > 2, 15.0, "PoseStamped while holding")
    pose, _ = poses.last()
    home = [pose.pose.position.x, pose.pose.position.y, pose.pose.position.z]
    o = pose.pose.orientation
    q = {"w": o.w, "x": o.x, "y": o.y, "z": o.z}
    target = [home[0] + 0.1, home[1], home[2]]

    flight = path([(0.0, home), (1.5, target)], q)
    s.put(key("/path", PATH, 0), flight, attachment=request_attachment(1))
    wait(lambda: verdicts.count() >= 1, 30.0, "the Path's verdict")
    verdict = json.loads(verdicts.last()[0].data)
    assert verdict["event"] == "trajectory_accepted", verdict

    def arrived() -> bool:
        p = poses.last()[0].pose.position
        return _state(diagnostics) == "hold" and abs(p.x - target[0]) < 2e-3

    wait(arrived, 20.0, "the Path flown")

    # the fly_path action: a long goal with feedback, cancelled midway: the robot holds
    feedback: list[Any] = []
    watched = s.declare_subscriber(
        FEEDBACK, lambda x: feedback.append(decode(x.payload.to_bytes(), "FeedbackMessage"))
    )
    client = Client(s, timeout=60.0)
    goal = new_id()
    away = [target[0] + 0.15, target[1], target[2]]
    slow = action_path((0.0, tuple(target)), (8.0, tuple(away)))
    assert client.send_goal(goal, slow).accepted
    ending = client.get_result(goal)
    wait(lambda: bool(feedback) and feedback[-1].feedback.progress > 0.1, 30.0, "feedback")
    assert client.cancel(goal).return_code == ERROR_NONE
    ended = ending()
    watched.undeclare()
    assert ended.status == CANCELED, ended
    wait(lambda: _state(diagnostics) == "hold", 10.0, "holding after the cancel")
    stopped = poses.last()[0].pose.position.x
    assert target[0] < stopped < away[0]  # midway
    progress = [f.feedback.progress for f in feedback]
    assert progress == sorted(progress) and 0.1 < progress[-1] < 1.0

    braked = trigger(s, service_key("/brake"), 2)
    assert braked.success, braked.message
    wait(lambda: _state(diagnostics) == "braked", 10.0, "braked")
    (status,) = diagnostics.last()[0].status
    assert status.level == 2  # ERROR
