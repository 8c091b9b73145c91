"""What `cdprd` commands print: --json (one object on stdout, the daemon's reply as a
stand-in daemon sent it, the demo's figures; errors as {"error": ...}, argparse's
refusals too), the progress line (a fake clock), `send --wait` following a short flight
to its end or its brake, the exit codes in every command's --help."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from cdpr import Pose, Robot
from cdpr.trajectory import Trajectory
from daemon.cli import command_parser, main
from daemon.cli.client_cmd import _watch_identify
from daemon.cli.completion import subcommands
from daemon.cli.exit_codes import codes_of
from daemon.cli.progress import ProgressLine, render
from daemon.config import load_config
from tests.daemon.test_zenoh_io import TRAJECTORY, Running, StandIn, cli
from tests.loopback import free_port

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
FLIGHT = 0.6  # s: the stand-in's flights


class Clock:
    """A clock the test moves."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def running() -> Iterator[Running]:
    served = Running(StandIn())
    yield served
    served.stop()


def out_json(capsys: pytest.CaptureFixture[str]) -> tuple[Any, str]:
    """The one JSON object on stdout, and stderr."""
    captured = capsys.readouterr()
    [line] = captured.out.splitlines()
    return json.loads(line), captured.err


# -- the progress line ----------------------------------------------------------------


def test_the_progress_line_renders_the_bar_phase_elapsed_and_eta() -> None:
    clock, stream = Clock(), io.StringIO()
    line = ProgressLine("send", True, stream, clock)
    clock.now += 10.0
    line.update(0.25, "flying")  # ETA extrapolated: 10 s for a quarter, 30 s to go
    assert stream.getvalue() == "\rsend  [######..................]  25%  flying  10s  ETA 30s"
    clock.now += 0.05
    line.update(0.3, "flying")  # within INTERVAL of the last draw: not redrawn
    assert stream.getvalue().count("\r") == 1
    clock.now += 65.0
    line.update(0.5, eta=2.4)  # the daemon's ETA wins; a shorter line blanks the rest
    last = stream.getvalue().rsplit("\r", 1)[1]
    assert last.rstrip() == "send  [############............]  50%  1m15s  ETA 2s"
    assert len(last) == len("send  [######..................]  25%  flying  10s  ETA 30s")
    line.note("a warning")  # a line of its own: the live line blanked first
    assert stream.getvalue().endswith("\r" + " " * len(last) + "\ra warning\n")
    line.close()  # nothing drawn since the note: no newline
    assert stream.getvalue().endswith("a warning\n")
    assert render("home", 3.0, None, "idle", None) == "home  idle  3s"  # no fraction, no ETA
    assert render("x", 7300.0, 0.0, "", None) == "x  [........................]   0%  2h01m"


def test_a_progress_line_not_enabled_writes_nothing_and_counts_steps() -> None:
    stream = io.StringIO()
    with ProgressLine("grid", False, stream) as line:
        line.update(0.5, "x")
        line.count(1, 2)
    assert stream.getvalue() == ""
    clock = Clock()
    with ProgressLine("grid", True, stream, clock) as line:
        line.count(1, 4)
        line.count(4, 4)  # the last step is always drawn, then the line ends
    last = stream.getvalue().rsplit("\r", 1)[1]
    assert last.rstrip() == "grid  [########################] 100%  4/4  0s"  # no ETA left
    assert last.endswith("\n")


def test_identify_payload_progress_counts_the_poses_from_the_daemons_events() -> None:
    class Subscribing:
        def __init__(self) -> None:
            self.callbacks: dict[str, Any] = {}

        def subscribe_events(self, callback: Any) -> str:
            self.callbacks["events"] = callback
            return "events"

        def subscribe_state(self, callback: Any) -> str:
            self.callbacks["state"] = callback
            return "state"

    client, clock, stream = Subscribing(), Clock(), io.StringIO()
    line = ProgressLine("identify-payload", True, stream, clock)
    assert _watch_identify(client, line) == ["events", "state"]  # type: ignore[arg-type]
    accepted = {"event": "state", "why": "goto accepted", "state": "tracking"}
    for _ in range(3):
        clock.now += 4.0
        client.callbacks["events"](accepted)
    client.callbacks["events"]({"event": "state", "why": "hold"})  # not a pose
    assert stream.getvalue().rsplit("\r", 1)[1].rstrip() == (
        "identify-payload  [########................]  33%  pose 3 of 5  12s  ETA 24s"
    )
    for _ in range(3):
        client.callbacks["events"](accepted)
    clock.now += 1.0
    client.callbacks["state"]({"state": "tracking"})
    assert "returning" in stream.getvalue().rsplit("\r", 1)[1]


# -- --json against the stand-in daemon -------------------------------------------------


def test_every_client_command_prints_the_daemons_reply_with_json(
    running: Running, capsys: pytest.CaptureFixture[str]
) -> None:
    handler = running.handler
    handler.refuse_enable = False
    commands = {
        "status": [],
        "enable": [],
        "disable": [],
        "hold": [],
        "reset": [],
        "brake": ["--reason", "test"],
        "goto": ["0.1", "0", "1.3"],
        "identify-payload": [],
        "payload": ["--freeze"],
        "observer": ["--hold"],
        "home": [],
        "pretension": [],
    }
    for command, argv in commands.items():
        assert cli(running, command, *argv, "--json") == 0, command
        out, err = out_json(capsys)
        name = command.replace("-", "_")
        assert handler.calls[-1][0] == name
        reply = {"state": "IDLE"} if name == "reset" else {"state": "IDLE", "command": name}
        assert out == reply  # the stand-in's reply, as it is
        assert err == ""
    # without --json: the same reply for a person (YAML)
    assert cli(running, "status") == 0
    assert yaml.safe_load(capsys.readouterr().out) == {"state": "IDLE", "command": "status"}


def test_json_errors_are_one_object_on_stdout_with_the_exit_code(
    running: Running, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli(running, "enable", "--json") == 1  # the stand-in refuses it
    out, err = out_json(capsys)
    assert out == {
        "error": {"code": "invalid_state", "reason": "cannot enable while BRAKED (reset first)"}
    }
    assert err == ""
    waypoints = TRAJECTORY["waypoints"]
    too_long = tmp_path / "long.json"
    too_long.write_text(json.dumps({"waypoints": [waypoints[0], {**waypoints[1], "t": 500}]}))
    assert cli(running, "send", str(too_long), "--json") == 1
    out, _ = out_json(capsys)
    assert out["error"] == {
        "code": "rejected",
        "reason": "too long for the stand-in",
        "limit": "max_duration",
    }
    assert cli(running, "goto", "1", "2", "--json") == 2  # usage: before any network
    out, _ = out_json(capsys)
    assert out["error"]["code"] == "usage" and "3 or 7 numbers" in out["error"]["reason"]
    assert cli(running, "status", "--prefix", "cdpr/nobody", "--json") == 3
    out, _ = out_json(capsys)
    assert out["error"]["code"] == "unreachable"
    assert "no daemon answered on cdpr/nobody/cmd/status" in out["error"]["reason"]
    assert cli(running, "enable") == 1  # without --json: the human line on stderr
    captured = capsys.readouterr()
    assert captured.out == ""
    assert (
        captured.err
        == "enable: refused (invalid_state): cannot enable while BRAKED (reset first)\n"
    )


class Procedure(StandIn):
    """A stand-in whose home takes a while (as the daemon's, at rest over cycles)."""

    def command(self, name: str, args: dict[str, Any]) -> Any:
        if name != "home":
            return super().command(name, args)
        self._record(name, args)

        async def home() -> dict[str, Any]:
            await asyncio.sleep(0.4)
            return {"pose": "home", "method": "home at pose home"}

        return home()


def test_home_shows_its_progress_from_the_state_and_prints_its_reply(
    capsys: pytest.CaptureFixture[str],
) -> None:
    served = Running(Procedure())
    try:
        assert cli(served, "home", "--json", "--progress") == 0
    finally:
        served.stop()
    out, err = out_json(capsys)
    assert out == {"pose": "home", "method": "home at pose home"}
    assert "\rhome  IDLE  0s" in err and err.endswith("\n")  # the stand-in's state


def test_check_config_json_has_every_figure_it_prints(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(CONFIG), "--json"]) == 0
    out, _ = out_json(capsys)
    config = load_config(CONFIG)
    robot = config.robot
    assert out["robot"]["name"] == robot.name == "reference8"
    assert out["robot"]["cables"] == 8 and out["robot"]["platform_mass"] == robot.platform.mass
    assert np.allclose(out["robot"]["cable_lengths_at_home"], robot.cable_lengths(robot.home))
    assert np.allclose(out["robot"]["modal_masses_at_home"], robot.modal_masses(robot.home))
    assert out["drives"]["nodes"] == list(config.drives.nodes)
    assert out["drives"]["protocol"] == "cia402" and out["drives"]["detection_s"] > 0.0
    assert len(out["drives"]["drift"]["bounds"]) == 8
    assert out["gains"]["pid"]["kp"] == config.controller.pid.kp
    assert out["gains"]["largest_stable_mass"] > out["gains"]["largest_modal_mass_at_home"]
    assert out["workspace"]["volume_at_home_m3"] > 0.0
    assert out["zenoh"] == {
        "prefix": "cdpr/reference8",
        "listen": list(config.zenoh.listen_endpoints),
    }
    assert out["buses"][0]["nodes"] == list(config.drives.nodes)
    assert isinstance(out["warnings"], list)
    # the same lines as before for a person; a robot file alone: the robot's figures
    assert main(["check-config", str(CONFIG)]) == 0
    assert capsys.readouterr().out.startswith("robot reference8: 8 cables, platform 10 kg\n")
    robot_file = ROOT / "config" / "robots" / "reference8.yaml"
    assert main(["check-config", str(robot_file), "--json"]) == 0
    out, _ = out_json(capsys)
    assert set(out) == {"robot"}
    assert out["robot"]["cables"] == Robot.from_yaml(robot_file).n_cables


def test_check_config_json_names_the_problems(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: nothing\n")
    assert main(["check-config", str(bad), "--json"]) == 1
    out, _ = out_json(capsys)
    assert out["error"]["code"] == "invalid_config"
    assert out["error"]["problems"] and all(str(bad) in p for p in out["error"]["problems"])
    assert main(["check-config", str(bad)]) == 1  # without --json: each on stderr
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith(f"error: {bad}")


# -- usage and config errors with --json -------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["analyze", "--config", str(CONFIG), "--grid", "99"], "--grid must be between 2 and 20"),
        (["analyze", "--grid", "3"], "the following arguments are required: --config"),
        (["tune", "--config", str(CONFIG), "--check-loads", "x"], "expected masses in kg"),
        (["workspace", "--config", str(CONFIG), "--step", "abc"], "invalid float value: 'abc'"),
        (["demo", "--plot"], "argument --plot: expected one argument"),
        (["status", "--timeout", "soon"], "invalid float value: 'soon'"),
    ],
    ids=["analyze-range", "analyze-missing", "tune", "workspace", "demo", "client"],
)
def test_argument_errors_with_json_are_one_object_on_stdout(
    argv: list[str], words: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """argparse's own refusals: with --json an error object on stdout and nothing on
    stderr; without, argparse's usage and message on stderr.  Exit code 2 either way."""
    with pytest.raises(SystemExit) as exited:
        main([*argv, "--json"])
    assert exited.value.code == 2
    out, err = out_json(capsys)
    assert out["error"]["code"] == "usage" and words in out["error"]["reason"]
    assert err == ""
    with pytest.raises(SystemExit) as exited:
        main(argv)
    assert exited.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("usage: cdprd") and "error: " in captured.err
    assert words in captured.err


@pytest.fixture
def root_logger_kept() -> Iterator[None]:
    """The root logger's handlers and level restored after the test (`demo` sets up the
    daemon's logging in this process)."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
    root.setLevel(level)


@pytest.mark.usefixtures("root_logger_kept")
def test_analyze_tune_workspace_and_demo_name_a_bad_config_as_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: nothing\n")
    for command in ("analyze", "tune", "workspace", "demo"):
        assert main([command, "--config", str(bad), "--json"]) == 1, command
        out, err = out_json(capsys)
        assert out["error"]["code"] == "invalid_config", command
        assert all(str(bad) in problem for problem in out["error"]["problems"]), command
        assert err == "", command


@pytest.mark.slow  # over 4.5 s (seven processes)
def test_tune_analyze_and_workspace_refusals_are_error_objects_with_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each refusal after the arguments parsed: {"error": ...} on stdout, exit code 1,
    and without --json the same reason on stderr."""
    blocker = tmp_path / "file"  # a file where a directory should be
    blocker.write_text("")
    robot = str(ROOT / "config" / "robots" / "reference8.yaml")
    tune = ["tune", "--config", str(CONFIG)]
    cases = [
        ([*tune, "--lockstep"], "usage", "--lockstep runs the simulator in simulated time"),
        ([*tune, "--plot", str(tmp_path / "no" / "t.png")], "usage", "t.png: no such directory"),
        ([*tune, "--drive", "99"], "usage", "--drive 99: the robot has cables 0..7"),
        (
            ["analyze", "--config", robot, "--grid", "2", "--plot", str(blocker)],
            "not_written",
            f"cannot write plots to {blocker}: ",
        ),
        (
            ["workspace", "--config", robot, "--step", "0.3", "--output", str(blocker / "m")],
            "not_written",
            f"cannot save the workspace map to {blocker / 'm'}: ",
        ),
    ]
    for argv, code, words in cases:
        assert main([*argv, "--json"]) == 1, argv
        out, err = out_json(capsys)
        assert out["error"]["code"] == code and words in out["error"]["reason"], argv
        assert err == "", argv
        assert main(argv) == 1, argv
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err.startswith("error: "), argv
        assert words in captured.err, argv


@pytest.mark.slow  # the demo flown, 20-30 s
@pytest.mark.timeout(120)
def test_demo_json_is_one_object_with_the_figures_it_prints() -> None:
    """`cdprd demo --json` as a process: stdout one object (the tracking error with its
    definition, the tensions, the daemon's cycle statistics), the live view's address on
    stderr."""
    view = free_port()
    run = subprocess.run(
        [sys.executable, "-m", "daemon.cli", "demo", "--json", "--view", f"127.0.0.1:{view}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=100,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    [line] = run.stdout.splitlines()
    out = json.loads(line)
    assert out["robot"] == "reference8" and out["cables"] == 8 and out["final_state"] == "hold"
    trajectory = out["trajectory"]
    assert trajectory["shape"] == "figure-eight" and trajectory["duration_s"] > 5.0
    error = out["tracking_error"]
    assert "same instant" in error["definition"]
    assert 0.0 < error["rms_mm"] <= error["max_mm"] and error["rms_mm"] < 2.0
    assert 0.0 < error["orientation_rms_deg"] <= error["orientation_max_deg"]
    assert out["tensions"]["slack_events"] == 0
    assert 0.0 < out["tensions"]["min_n"] < out["tensions"]["max_n"]
    cycle = out["cycle"]
    assert cycle["cycles"] >= trajectory["duration_s"] * cycle["rate_hz"]  # flown throughout
    assert cycle["deadline_misses"] >= 0 and cycle["overruns"] >= 0
    assert 0.0 < cycle["compute"]["p50_us"] <= cycle["compute"]["p99_us"]
    assert cycle["latency"]["p50_us"] <= cycle["latency"]["p99_us"]
    assert (out["plot"], out["drawing"], out["telemetry"]) == (None, None, None)
    assert f"live view: ws://127.0.0.1:{view}" in run.stderr


# -- send --wait ------------------------------------------------------------------------


class Flying(StandIn):
    """A stand-in that flies what it accepts as the daemon does: the reply's start, end
    and duration on its clock (the state's "t"), TRACKING between them and the motion
    its client's, then HOLD; with `brake_after`, BRAKED that long into the flight."""

    def __init__(self, brake_after: float | None = None) -> None:
        super().__init__()
        self.t0 = time.monotonic()
        self.flight: tuple[float, float, Any] | None = None
        self.brake_after = brake_after

    def now(self) -> float:
        return time.monotonic() - self.t0

    def submit_trajectory(self, trajectory: Trajectory, start: float | None, claim: Any) -> Any:
        self._record("trajectory", trajectory, start, claim)
        begin = self.now() + 0.05
        end = begin + trajectory.duration
        self.flight = (begin, end, claim)
        return {"accepted": True, "what": "trajectory", "start": begin, "end": end,
                "duration": trajectory.duration}  # fmt: skip

    def state(self) -> dict[str, Any]:
        t, state, motion, fault = self.now(), "hold", None, None
        if self.flight is not None:
            begin, end, claim = self.flight
            braked = self.brake_after is not None and t >= begin + self.brake_after
            if braked:
                state, fault = "braked", {"trigger": "command", "message": "the test"}
            elif t < end:
                state = "tracking" if t >= begin else "hold"
                motion = {"what": "trajectory", "client": claim.client, "id": claim.id}
        return {"t": t, "state": state, "fault": fault, "motion": motion,
                "pose": Pose((0.0, 0.0, 1.25)).as_dict()}  # fmt: skip


def short_flight(tmp_path: Path) -> Path:
    path = tmp_path / "short.json"
    waypoints = TRAJECTORY["waypoints"]
    path.write_text(json.dumps({"waypoints": [waypoints[0], {**waypoints[1], "t": FLIGHT}]}))
    return path


def test_send_wait_follows_the_flight_to_its_end(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = Running(Flying())
    try:
        argv = ("send", str(short_flight(tmp_path)), "--id", "w-1", "--wait", "--json")
        assert cli(served, *argv, "--progress") == 0
        done = time.monotonic() - served.handler.t0
        out, err = out_json(capsys)
    finally:
        served.stop()
    accepted = out["result"]
    assert out["id"] == "w-1" and accepted["duration"] == pytest.approx(FLIGHT)
    # waited until the state showed the flight over, holding its last pose
    assert out["outcome"]["state"] == "hold" and out["outcome"]["fault"] is None
    assert accepted["end"] <= out["outcome"]["t"] <= done
    # the progress line on stderr (--progress), never on stdout
    assert "\rsend  [" in err and "flying" in err and "ETA" in err and err.endswith("\n")


def test_send_wait_exits_1_naming_the_brake(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = Running(Flying(brake_after=0.2))
    try:
        assert cli(served, "send", str(short_flight(tmp_path)), "--wait", "--json") == 1
        out, err = out_json(capsys)
        assert cli(served, "send", str(short_flight(tmp_path)), "--wait") == 1
        human = capsys.readouterr()
    finally:
        served.stop()
    error = out["error"]
    assert error["code"] == "braked" and error["state"] == "braked"
    assert error["fault"] == {"trigger": "command", "message": "the test"}
    assert "command: the test" in error["reason"] and error["accepted"]["duration"] == FLIGHT
    assert err == ""  # not a terminal, no --progress: no progress line
    assert human.out == ""
    assert "send: braked: the robot braked (command: the test)" in human.err


def test_send_without_wait_returns_at_the_reply(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    served = Running(Flying())
    try:
        began = time.monotonic()
        assert cli(served, "send", str(short_flight(tmp_path)), "--json") == 0
        took = time.monotonic() - began
    finally:
        served.stop()
    out, _ = out_json(capsys)
    assert "outcome" not in out and took < FLIGHT + 2.0  # generous on a loaded machine
    assert served.handler.calls[-1][0] == "trajectory"


# -- exit codes in --help ---------------------------------------------------------------


def test_every_command_names_its_exit_codes_in_its_help() -> None:
    for name, parser in subcommands(command_parser()).items():
        text = parser.format_help()
        assert "exit codes: " in text, name
        for code in codes_of(name):
            assert f"{code} " in text.split("exit codes: ", 1)[1], (name, code)
