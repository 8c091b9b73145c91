"""`cdprd home` and `cdprd calibrate` through the command line against a daemon process
(`cdprd run --sim`) over zenoh on loopback (issue 16 items 2 and 4)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from daemon.service.calibration_state import state_path
from tests.loopback import free_port
from tests.processes import CONFIG, ROOT, connect, finish, start_daemon, wait_status


def cdprd(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """`python -m daemon.cli ARGS` from this checkout, to its end."""
    command = [sys.executable, "-m", "daemon.cli", *args]
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def config_file(tmp_path: Path, port: int) -> Path:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["state_dir"] = str(tmp_path / "state")
    data["realtime"] = {"lock_memory": False}
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.timeout(240)
def test_home_then_calibrate_with_too_few_poses_names_what_is_unidentifiable(
    tmp_path: Path,
) -> None:
    """Home through the CLI (offsets stored), enable, then calibrate flying 8 poses
    through the daemon: 16 redundant lengths cannot identify 52 parameters, and the
    command says which, exits 1, and writes no robot file."""
    port = free_port()
    path = config_file(tmp_path, port)
    daemon = start_daemon(path, "--sim")
    try:
        client = connect(port, daemon)
        wait_status(client, "idle", 30.0)
        connection = ("--connect", f"tcp/127.0.0.1:{port}")
        homed = cdprd("home", *connection)
        assert homed.returncode == 0, homed.stderr
        result = json.loads(homed.stdout)
        assert result["method"] == "home at pose home" and len(result["offsets"]) == 8
        stored = json.loads(state_path(tmp_path / "state", "reference8").read_text())
        assert stored["offsets"] == result["offsets"]
        assert cdprd("enable", *connection).returncode == 0
        output = tmp_path / "calibrated.yaml"
        run = cdprd(
            "calibrate", "--config", str(path), "--poses", "8", "--dwell", "0.6",
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
        client.close()
    finally:
        finish(daemon)


def test_calibrate_never_overwrites_a_robot_file(tmp_path: Path) -> None:
    path = config_file(tmp_path, free_port())
    output = tmp_path / "robot.yaml"
    output.write_text("mine\n")
    run = cdprd("calibrate", "--config", str(path), "--output", str(output))
    assert run.returncode == 2
    assert f"error: {output} exists: not overwritten" in run.stderr
    assert output.read_text() == "mine\n"


@pytest.mark.parametrize("average", ["2.0", "0", "-1"])
def test_calibrate_averages_within_the_dwell(tmp_path: Path, average: str) -> None:
    path = config_file(tmp_path, free_port())
    run = cdprd("calibrate", "--config", str(path), "--dwell", "1.0", "--average", average)
    assert run.returncode == 2
    assert "usage error: --average: more than 0 s, at most --dwell (1 s)" in run.stderr
