"""Paths over zenoh (`<prefix>/path`): poses without times, which the interface times
within the robot's tensions (daemon.service.planner.path_timer) in its parse thread and
hands to the daemon as the trajectory to run; bad paths are refused naming the pose and
the limit, and never reach the handler."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cdpr.path import parse_path
from daemon.config import DaemonConfig, load_config
from daemon.interface.zenoh_io import DECODE_ON_ARRIVAL_BYTES
from daemon.service.api import Claim
from daemon.service.planner import path_timer
from tests.daemon.test_zenoh_io import IDENTITY, Running, StandIn, ask, cli, wait_until

CONFIG = Path(__file__).resolve().parents[2] / "config" / "reference8-cia402.yaml"
CORNER = {
    "version": 1,
    "id": "corner-1",
    "client": "alice@bench:1",
    "poses": [
        {"position": [0.0, 0.0, 1.25], "quaternion": IDENTITY},
        {"position": [0.2, 0.0, 1.25], "blend": 0.05},
        {"position": [0.2, 0.2, 1.3]},
    ],
}


@pytest.fixture(scope="module")
def config() -> DaemonConfig:
    return load_config(CONFIG)


@pytest.fixture
def timing(config: DaemonConfig) -> Iterator[Running]:
    served = Running(StandIn(), timer=path_timer(config))
    yield served
    served.stop()


def handed(running: Running) -> list[tuple]:
    return [c for c in running.handler.calls if c[0] == "trajectory"]


def test_a_path_reaches_the_handler_timed_as_the_daemon_times_it(
    timing: Running, config: DaemonConfig
) -> None:
    """By query: the reply and the handler's trajectory are the path timed (the same
    duration as path_timer gives offline: `cdprd plan`), from the first pose to the last,
    with the sender's claim."""
    with timing.session() as session:
        reply = ask(session, "path", json.dumps(CORNER))
    assert reply["ok"] and reply["zenoh_ok"], reply
    [(_, trajectory, start, claim)] = handed(timing)
    offline = path_timer(config)(parse_path({"poses": CORNER["poses"]}))
    assert trajectory.duration == pytest.approx(offline.duration, rel=1e-12)
    assert np.allclose(trajectory.sample(trajectory.start_time).pose.position, [0, 0, 1.25])
    assert np.allclose(trajectory.sample(trajectory.end_time).pose.position, [0.2, 0.2, 1.3])
    assert start is None and claim == Claim("alice@bench:1", False, "corner-1")


def test_a_long_path_put_is_parsed_and_timed_in_the_parse_thread(timing: Running) -> None:
    """A put of 200 poses, too long to decode on zenoh's thread: queued undecoded as a
    path, timed in the parse thread, handed to the handler (never on its loop thread's
    own parse: the loop only submits)."""
    poses = [{"position": [0.0, 0.0, 1.0], "quaternion": IDENTITY}]
    for k in range(1, 200):
        x, y = 0.2 * ((k % 4) in (1, 2)), 0.2 * ((k % 4) >= 2)
        poses.append({"position": [x, y, 1.0 + 0.002 * k], "blend": 0.03})
    body = json.dumps({"version": 1, "poses": poses})
    assert len(body) > DECODE_ON_ARRIVAL_BYTES
    with timing.session() as session:
        session.put(f"{timing.prefix}/path", body)
        wait_until(lambda: handed(timing), "the timed path")
    [(_, trajectory, _, _)] = handed(timing)
    end = trajectory.sample(trajectory.end_time).pose.position
    assert np.allclose(end, poses[-1]["position"]) and trajectory.duration > 10.0


HOME = {"position": [0.0, 0.0, 1.25], "quaternion": IDENTITY}
BAD_PATHS = [
    ([HOME, {"position": [2, 2, 2.2]}], "path_infeasible"),  # beside an anchor: no tensions
    ([{"position": [0.0, 0.0, 1.25]}], "poses[0]"),  # the first pose needs its quaternion
    ([HOME, {"position": [0, "x", 1]}], "poses[1].position"),
    ([HOME, {"position": [0.1, 0, 1.25], "speed": -1}], "poses[1].speed"),
]


@pytest.mark.parametrize(("poses", "words"), BAD_PATHS)
def test_a_bad_path_is_refused_naming_the_pose_and_never_handed_over(
    timing: Running, poses: list, words: str
) -> None:
    with timing.session() as session:
        reply = ask(session, "path", json.dumps({"version": 1, "id": "bad", "poses": poses}))
    assert not reply["ok"] and not reply["zenoh_ok"] and reply["id"] == "bad"
    assert words in json.dumps(reply["error"]), reply
    assert handed(timing) == []


def test_a_trajectory_sent_as_a_path_is_refused(timing: Running) -> None:
    """Each key takes its own message: waypoints on the path key are no poses."""
    trajectory = {"version": 1, "waypoints": [{"t": 0.0, "position": [0, 0, 1.25]}]}
    with timing.session() as session:
        reply = ask(session, "path", json.dumps(trajectory))
    assert not reply["ok"] and "poses" in json.dumps(reply["error"]), reply
    assert handed(timing) == []


def test_an_interface_without_a_timer_refuses_paths() -> None:
    served = Running(StandIn())
    try:
        with served.session() as session:
            reply = ask(session, "path", json.dumps(CORNER))
        assert not reply["ok"] and "takes no paths" in json.dumps(reply["error"]), reply
        assert handed(served) == []
    finally:
        served.stop()


def test_cdprd_send_path_and_gcode(
    timing: Running, config: DaemonConfig, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cdprd send --path` sends a path file as it is; `--gcode --config` reads G-code
    from the robot's home as `cdprd plan` does and sends it as a path; bad G-code names
    its line and --gcode without a config is refused, both before any network."""
    path_file = tmp_path / "corner.json"
    path_file.write_text(json.dumps({"poses": CORNER["poses"]}))
    assert cli(timing, "send", str(path_file), "--path", "--id", "c-1", "--json") == 0
    assert json.loads(capsys.readouterr().out)["id"] == "c-1"
    program = tmp_path / "square.gcode"
    program.write_text("G21 G90\nG1 X100 F6000\nG1 Y100\nG4 P200\nG1 X0\n")
    argv = ("send", str(program), "--gcode", "--config", str(CONFIG), "--blend", "0.01")
    assert cli(timing, *argv) == 0
    [first, second] = [c[1] for c in handed(timing)]
    end = second.sample(second.end_time).pose.position
    assert np.allclose(end, [0.0, 0.1, config.robot.home.position[2]])  # world mm, G90
    assert first.duration > 0.0
    program.write_text("G1 X100\nM3 S1000\n")
    assert cli(timing, *argv) == 2
    assert "line 2" in capsys.readouterr().err
    assert cli(timing, "send", str(program), "--gcode") == 2
    assert "--gcode needs --config" in capsys.readouterr().err
    assert len(handed(timing)) == 2


def test_the_daemon_imports_the_path_timing_only_when_a_path_comes(config: DaemonConfig) -> None:
    """matplotlib costs 1.7 s and log lines at the daemon's start (which broke the UML
    guest's log-length check, when the path timing imported toppra and toppra imported
    it): the daemon's processes and the path timer import neither; toppra is only the
    tests' reference for the timing's passes (tests/cdpr/test_reachability.py)."""
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "import daemon.process.app, daemon.process.companion, daemon.cli\n"
        "from daemon.config import load_config\n"
        "from daemon.service.planner import path_timer\n"
        f"path_timer(load_config({str(CONFIG)!r}))\n"
        "print(sorted({'toppra', 'matplotlib'} & set(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"
