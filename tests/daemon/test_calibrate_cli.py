"""`cdprd home` and `cdprd calibrate` through the command line against a daemon process
(`cdprd run --sim`) over zenoh on loopback, and the external
wrench observer held out of the loop while calibrating (the `observer` command)."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from daemon.interface.client import CdprClient, RequestError
from daemon.service.calibration_state import state_path
from tests.loopback import free_port
from tests.processes import CONFIG, ROOT, cdprd, connect, finish, start_daemon, wait_status

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)


def config_file(tmp_path: Path, port: int, push: float = 0.0) -> Path:
    """The reference8 CiA 402 config with zenoh on `port`, a state directory, and a
    constant push of `push` N along x on the simulated platform."""
    data = yaml.safe_load(CONFIG.read_text())
    data["sim"]["plant"]["disturbance"] = {"wrench": [push, 0.0, 0.0, 0.0, 0.0, 0.0]}
    # the push acts from the start: the rest check at enable must allow for it
    data["safety"]["rest_force"] = 30.0 + abs(push)
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["state_dir"] = str(tmp_path / "state")
    data["realtime"] = {"lock_memory": False}
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


# a real-time flight through three processes: a clean-clone run braked once on stale feedback
@pytest.mark.host_timing
@pytest.mark.timeout(240)
def test_home_then_calibrate_with_too_few_poses_names_what_is_unidentifiable(
    tmp_path: Path,
) -> None:
    """Home through the CLI (offsets stored), enable, then calibrate flying 8 poses
    through the daemon: 16 redundant lengths cannot identify 52 parameters, and the
    command says which, exits 1, and writes no robot file."""
    port = free_port()
    path = config_file(tmp_path, port)
    daemon = start_daemon(path, "--sim", log=tmp_path / "daemon.log")
    try:
        with connect(port, daemon) as client:  # closed on a failure too
            wait_status(client, "idle", 30.0)
            connection = ("--connect", f"tcp/127.0.0.1:{port}")
            homed = cdprd("home", *connection, "--json")
            assert homed.returncode == 0, homed.stderr
            result = json.loads(homed.stdout)
            assert result["method"] == "home at pose home" and len(result["offsets"]) == 8
            stored = json.loads(state_path(tmp_path / "state", "reference8").read_text())
            assert stored["offsets"] == result["offsets"]
            assert cdprd("enable", *connection).returncode == 0
            output = tmp_path / "calibrated.yaml"
            run = cdprd(
                "calibrate", "--config", str(path), "--no-scale", "--poses", "8", "--dwell", "0.6",
                "--output", str(output), *connection,
            )  # fmt: skip
            assert run.returncode == 1, run.stderr
            recorded = run.stderr.count(" recorded\n")
            assert recorded + run.stderr.count(" skipped: ") == 8 and recorded >= 4
            unknown = 52 - 2 * recorded  # each pose: 8 lengths, 6 of them for its own pose
            assert (
                f"error: {recorded} poses do not identify every parameter ({unknown} combinations"
                in run.stderr
            )
            assert "anchors of cables" in run.stderr
            assert not output.exists()
    finally:
        finish(daemon)


def test_calibrate_never_overwrites_a_robot_file(tmp_path: Path) -> None:
    path = config_file(tmp_path, free_port())
    output = tmp_path / "robot.yaml"
    output.write_text("mine\n")
    run = cdprd("calibrate", "--config", str(path), "--no-scale", "--output", str(output))
    assert run.returncode == 2
    assert f"error: {output} exists: not overwritten" in run.stderr
    assert output.read_text() == "mine\n"


@pytest.mark.parametrize("average", ["2.0", "0", "-1"])
def test_calibrate_averages_within_the_dwell(tmp_path: Path, average: str) -> None:
    path = config_file(tmp_path, free_port())
    run = cdprd("calibrate", "--config", str(path), "--dwell", "1.0", "--average", average)
    assert run.returncode == 2
    assert "usage error: --average: more than 0 s, at most --dwell (1 s)" in run.stderr


def _until(condition: Any, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"never {what}"
        time.sleep(0.05)


@pytest.mark.timeout(120)
def test_the_observer_is_held_out_of_the_loop_through_zenoh(tmp_path: Path) -> None:
    """A 30 N push on the simulated platform: the observer takes it in.  Held through
    zenoh, the state says so and its estimate reads zero and takes nothing in while the
    integral action holds the push (the robot holding, no brake); let back in (`cdprd
    observer --release`), it takes the push in again.  Bad input is refused naming the key."""
    port = free_port()
    daemon = start_daemon(config_file(tmp_path, port, push=30.0), "--sim")
    try:
        # closed on a failure too: a session left open hangs pytest's exit
        with connect(port, daemon) as client:
            wait_status(client, "idle", 30.0)
            client.enable()
            states: list[dict[str, Any]] = []
            lock = threading.Lock()

            def on_state(state: dict[str, Any]) -> None:
                with lock:
                    states.append(state)

            def last() -> dict[str, Any]:
                with lock:
                    return states[-1] if states else {"observer_held": None}

            subscriber = client.subscribe_state(on_state)
            _until(lambda: (last().get("external_wrench") or [0.0])[0] > 25.0, 20.0, "pushed")
            assert last()["observer_held"] is False
            reply = client.observer(True)
            assert reply == {"held": True, "estimate": [0.0] * 6}
            _until(lambda: last()["observer_held"] is True, 5.0, "held in the state")
            with lock:
                start = len(states) - 1
            time.sleep(1.5)
            with lock:
                held = states[start:]
            assert len(held) >= 20  # 50 Hz for 1.5 s, on a loaded machine
            assert all(s["observer_held"] is True for s in held)
            assert all(s["external_wrench"] == [0.0] * 6 for s in held), held[-1]["external_wrench"]
            assert all(s["state"] == "hold" for s in held), held[-1]["fault"]
            assert client.observer() == {"held": True, "estimate": [0.0] * 6}
            released = cdprd(
                "observer", "--release", "--json", "--connect", f"tcp/127.0.0.1:{port}"
            )
            assert released.returncode == 0 and json.loads(released.stdout)["held"] is False
            _until(lambda: last()["observer_held"] is False, 5.0, "let back in")
            _until(lambda: last()["external_wrench"][0] > 25.0, 20.0, "the push taken in again")
            assert last()["state"] == "hold"
            subscriber.undeclare()
            for body, field, words in (
                ({"held": "yes"}, "held", "observer.held: expected true or false"),
                (
                    {"hold": True},
                    "observer",
                    "unknown key(s) 'hold' (allowed: version, client, held, lease, lease_id)",
                ),
            ):
                with pytest.raises(RequestError) as refused:
                    client.request("observer", body)
                assert refused.value.code == "bad_request" and words in refused.value.reason
                assert refused.value.reply["error"].get("field") == field
            assert client.observer()["held"] is False
    finally:
        finish(daemon)


@contextlib.contextmanager
def _enabled_daemon(tmp_path: Path) -> Iterator[tuple[CdprClient, Path, int]]:
    """`cdprd run --sim` on `config_file`'s config, enabled: a client, the config, the
    port; the daemon stopped after."""
    port = free_port()
    path = config_file(tmp_path, port)
    daemon = start_daemon(path, "--sim")
    try:
        with connect(port, daemon) as client:
            wait_status(client, "idle", 30.0)
            client.enable()
            yield client, path, port
    finally:
        finish(daemon)


def _calibrating(
    client: CdprClient, tmp_path: Path, config: Path, port: int, output: int
) -> subprocess.Popen:
    """`cdprd calibrate` flying 8 poses against the daemon on `port` (stdout and stderr to
    `output`), once `client` sees the observer held out of the loop (AssertionError and
    calibrate killed if never)."""
    command = [
        sys.executable, "-m", "daemon.cli", "calibrate", "--config", str(config), "--no-scale",
        "--poses", "8", "--dwell", "0.6", "--output", str(tmp_path / "robot.yaml"),
        "--connect", f"tcp/127.0.0.1:{port}",
    ]  # fmt: skip
    calibrate = subprocess.Popen(command, cwd=ROOT, stdout=output, stderr=output, text=True)
    try:
        _until(lambda: client.observer()["held"], 60.0, "held by calibrate")
    except BaseException:
        calibrate.kill()
        calibrate.communicate(timeout=30)
        raise
    return calibrate


@pytest.mark.timeout(180)
@pytest.mark.parametrize("ending", ["brake", "sigterm"])
def test_calibrate_lets_the_observer_and_the_payload_go_however_it_ends(
    tmp_path: Path, ending: str
) -> None:
    """`cdprd calibrate` holds the observer out of the loop and freezes the payload
    estimate while it flies; the daemon braking under it, or SIGTERM to it, ends it
    with exit code 1, and both are let go."""
    with _enabled_daemon(tmp_path) as (client, path, port):
        assert client.observer()["held"] is False
        calibrate = _calibrating(client, tmp_path, path, port, subprocess.PIPE)
        try:
            assert client.observer()["held"] is True and client.payload()["frozen"] is True
            if ending == "brake":
                client.brake("the test")
            else:
                calibrate.send_signal(signal.SIGTERM)
            _, stderr = calibrate.communicate(timeout=60)
        finally:
            if calibrate.poll() is None:
                calibrate.kill()
        assert calibrate.returncode == 1, stderr
        assert "error: " in stderr
        if ending == "sigterm":
            assert "error: terminated (SIGTERM)" in stderr
        else:  # the brake, not the refusal of the next trajectory it causes
            assert "of 8: the daemon braked on command: the test\n" in stderr, stderr
            assert "while braked" not in stderr
        assert client.observer()["held"] is False
        assert client.payload()["frozen"] is False
        assert not (tmp_path / "robot.yaml").exists()


@pytest.mark.timeout(180)
def test_a_killed_calibrate_leaves_the_daemon_letting_go_within_its_lease(
    tmp_path: Path,
) -> None:
    """`kill -9` of a flying `cdprd calibrate`: nothing of it runs to let go, and the
    daemon does on its own when the lease calibrate renewed lapses: the payload unfrozen
    and the observer back in, one `lease_lapsed` event for each naming calibrate's lease,
    the state's leases counted down to none; the robot keeps holding.  A bad lease is
    refused through zenoh naming the key."""
    from daemon.cli.calibrate_cmd import LEASE

    with _enabled_daemon(tmp_path) as (client, path, port):
        events: list[dict[str, Any]] = []
        states: list[dict[str, Any]] = []
        lock = threading.Lock()

        def keep(into: list[dict[str, Any]]) -> Any:
            def append(message: dict[str, Any]) -> None:
                with lock:
                    into.append(message)

            return append

        subscribers = [client.subscribe_events(keep(events)), client.subscribe_state(keep(states))]

        def lapsed() -> dict[str, dict[str, Any]]:
            with lock:
                return {e["what"]: e for e in events if e["event"] == "lease_lapsed"}

        def last() -> dict[str, Any]:
            with lock:
                return states[-1]

        calibrate = _calibrating(client, tmp_path, path, port, subprocess.DEVNULL)
        try:
            assert client.observer()["held"] is True and client.payload()["frozen"] is True

            def held_leases() -> list[dict[str, float]]:
                with lock:
                    return [s["leases"] for s in states if s["observer_held"]]

            # the published state says so a cycle or more after the companion does (CI
            # killed calibrate before any state had it)
            _until(lambda: bool(held_leases()), 10.0, "held in the published state")
            calibrate.kill()
            assert calibrate.wait(timeout=30) == -signal.SIGKILL
            held = held_leases()
            assert held and all(0.0 < h["observer"] <= LEASE for h in held[-5:]), held[-5:]
            assert all(0.0 < h["payload"] <= LEASE for h in held[-5:]), held[-5:]
            _until(lambda: len(lapsed()) == 2, 10.0 * LEASE, "let go by the lease")
        finally:
            if calibrate.poll() is None:
                calibrate.kill()
        assert client.observer()["held"] is False
        assert client.payload()["frozen"] is False
        assert {what: e["lease"] for what, e in lapsed().items()} == {
            "payload": LEASE,
            "observer": LEASE,
        }
        # the leases are the companion's, observer_held the core's (a cycle or more later)
        _until(
            lambda: (
                last()["leases"] == {"payload": None, "observer": None}
                and last()["observer_held"] is False
            ),
            10.0,
            "none left",
        )
        assert last()["state"] == "hold"
        for subscriber in subscribers:
            subscriber.undeclare()
        with pytest.raises(RequestError) as refused:
            client.request("observer", {"held": True, "lease": 0})
        assert refused.value.code == "bad_request"
        assert refused.value.reply["error"].get("field") == "lease"
        assert "observer.lease: 0 s: must be more than 0" in refused.value.reason
        assert client.observer()["held"] is False


def _recorded(kept: Path) -> int:
    """Poses recorded in the round file `kept` (0: none yet)."""
    return len(json.loads(kept.read_text())["recorded"]) if kept.exists() else 0


@pytest.mark.timeout(300)
def test_a_brake_mid_round_keeps_the_poses_and_resume_flies_the_rest(tmp_path: Path) -> None:
    """The daemon braked once calibrate has recorded two of its 8 poses: calibrate ends
    naming the brake's trigger and message, keeps the poses recorded in the round file
    and says what they identify so far.  Reset and enabled, `--resume` flies only the
    poses not flown yet and solves with all of them (8 poses cannot identify every
    parameter: refused naming 8), and the round is over: its file removed."""
    with _enabled_daemon(tmp_path) as (client, path, port):
        kept = tmp_path / "state" / "reference8.calibration-round.json"
        calibrate = _calibrating(client, tmp_path, path, port, subprocess.PIPE)
        try:
            _until(lambda: _recorded(kept) >= 2, 120.0, "two poses recorded")
            client.brake("a cable snagged (the test)")
            _, stderr = calibrate.communicate(timeout=60)
        finally:
            if calibrate.poll() is None:
                calibrate.kill()
        assert calibrate.returncode == 1, stderr
        assert "the daemon braked on command: a cable snagged (the test)\n" in stderr
        round_ = json.loads(kept.read_text())
        recorded, skipped = len(round_["recorded"]), len(round_["skipped"])
        assert recorded >= 2 and stderr.count(" recorded\n") == recorded
        assert f"{recorded} of 8 poses recorded, kept in {kept}: reset and enable" in stderr
        assert f"so far the {recorded} poses recorded identify {2 * recorded} of 52" in stderr
        assert client.observer()["held"] is False and client.payload()["frozen"] is False
        connection = ("--connect", f"tcp/127.0.0.1:{port}")
        assert cdprd("calibrate", "--config", str(path), "--no-scale", *connection).returncode == 1
        client.reset()
        client.enable()
        wait_status(client, "hold", 10.0)
        resumed = cdprd(
            "calibrate", "--config", str(path), "--no-scale", "--resume", "--dwell", "0.6",
            "--output", str(tmp_path / "robot.yaml"), *connection,
        )  # fmt: skip
        assert resumed.returncode == 1, resumed.stderr
        left = 8 - recorded - skipped
        assert (
            f"resuming the round in {kept}: {recorded} of 8 poses recorded, {left} to fly"
            in resumed.stderr
        )
        flown = resumed.stderr.count(" recorded\n")
        assert flown + resumed.stderr.count(" skipped: ") == left
        assert f"error: {recorded + flown} poses do not identify every parameter" in resumed.stderr
        assert not kept.exists()
