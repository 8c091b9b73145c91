"""`cdprd run --sim` as its own process with a state directory it cannot trust: the
daemon never blocks on a file and never takes a refused one's offsets; it starts, says in
one line which file and why, and refuses enable until homed.  And `home` at a pose the
platform is not resting at is refused over zenoh, the stored state untouched."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
import yaml

from daemon.interface.client import RequestError
from tests.loopback import free_port
from tests.processes import CONFIG, ROOT, connect, finish, start_daemon, wait_status

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]  # two daemon starts on a loaded host
STATE_FILE = "reference8.calibration.json"


def sim_config(tmp_path: Path, port: int) -> Path:
    """The reference8 example on zenoh `port`, state in tmp_path/state, its robot file
    with a pose "high" 0.3 m above home (where the simulated platform starts)."""
    data = yaml.safe_load(CONFIG.read_text())
    robot = yaml.safe_load((ROOT / "config" / "robots" / "reference8.yaml").read_text())
    robot["poses"] = {"high": {"position": [0.0, 0.0, 1.55]}}
    data["robot"] = robot
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_state_file_that_is_a_fifo_is_named_and_start_up_goes_on(tmp_path: Path) -> None:
    """A FIFO in place of the state file used to block the core in its open(): the
    companion waited for it for ever, with no log line."""
    port = free_port()
    config = sim_config(tmp_path, port)
    (tmp_path / "state").mkdir()
    fifo = tmp_path / "state" / STATE_FILE
    os.mkfifo(fifo)
    proc = start_daemon(config, "--sim", log=tmp_path / "daemon.log")
    try:
        client = connect(port, proc, timeout=90.0)
        with client:
            status = wait_status(client, "idle", 30.0)
            assert (
                f"{fifo}: cannot read: a FIFO (named pipe), not a regular file"
                in (status["offsets"]["invalid"])
            )
            with pytest.raises(RequestError, match="home first"):
                client.enable()
            time.sleep(0.2)
    finally:
        finish(proc)
    log = (tmp_path / "daemon.log").read_text().splitlines()
    named = [line for line in log if "named pipe" in line]
    assert len(named) == 1 and str(fifo) in named[0], named


def test_an_edited_state_file_is_refused_and_home_at_a_pose_elsewhere_too(tmp_path: Path) -> None:
    """Homed, the offsets on disk edited by 300 mm (the finding): the daemon started again
    refuses the file naming its checksum and refuses enable; `home` at a pose 0.3 m above
    where the platform rests is refused naming the tensions' check, the file untouched."""
    port = free_port()
    config = sim_config(tmp_path, port)
    path = tmp_path / "state" / STATE_FILE
    proc = start_daemon(config, "--sim", log=tmp_path / "first.log")
    try:
        with connect(port, proc, timeout=90.0) as client:
            wait_status(client, "idle", 30.0)
            client.home()
    finally:
        finish(proc)
    data = json.loads(path.read_text())
    data["offsets"] = [x + 0.3 for x in data["offsets"]]
    path.write_text(json.dumps(data))
    edited = path.read_text()
    proc = start_daemon(config, "--sim", log=tmp_path / "second.log")
    try:
        with connect(port, proc, timeout=90.0) as client:
            status = wait_status(client, "idle", 30.0)
            assert f"{path}: checksum: does not match the content" in status["offsets"]["invalid"]
            with pytest.raises(RequestError, match="home first"):
                client.enable()
            with pytest.raises(RequestError, match="not resting at pose 'high': the tensions"):
                client.home("high")
            assert path.read_text() == edited
    finally:
        finish(proc)
