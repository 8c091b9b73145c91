"""`cdprd run --sim` as its own process recording onto a 2 MB tmpfs (both recordings, at
500 Hz about 0.85 GB an hour: full in seconds).  With no free-space floor the disk
fills: both recorders pause ("disk full"); with recording.min_free_mb 1 they pause at
the floor first ("floor reached").  Either way the daemon runs on, holding: status
answers every time and names each paused recorder and why, the published state carries
the same, an event says so, and the robot flies a trajectory as before.

Needs root (or CAP_SYS_ADMIN) to mount the tmpfs; skipped, saying so, where mounting is
not permitted."""

from __future__ import annotations

import contextlib
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from daemon.interface.client import CdprClient
from tests.loopback import free_port
from tests.processes import (
    PREFIX,
    ROOT,
    connect,
    finish,
    patient_watchdogs,
    start_daemon,
    wait_status,
)

CONFIG = ROOT / "config" / "reference8-cia402.yaml"
SIZE = "2m"

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]


@contextlib.contextmanager
def small_disk(where: Path) -> Iterator[Path]:
    """A 2 MB tmpfs mounted at `where` for the test's duration (skip if not permitted)."""
    where.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={SIZE}", "tmpfs", str(where)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs (needs root): {mounted.stderr.strip()}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], check=False).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], check=False)


def _config(tmp_path: Path, port: int, recording: dict) -> Path:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    # a loaded host's other real-time processes starving the daemon are not the point
    patient_watchdogs(data)
    data["safety"]["companion_hang"] = 10.0
    data["recording"] = recording
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _paused(status: dict) -> bool:
    recording = status.get("recording", {})
    return bool(recording) and all(r["status"] == "paused" for r in recording.values())


@pytest.mark.parametrize(
    ("floor_mb", "names", "reason"),
    [
        (0, ("telemetry", "can_log"), "disk full: "),
        # the raw CAN log (~0.7 MB/s) would fill the 1 MB left between two looks (1 s)
        (1, ("telemetry",), "floor reached: "),
    ],
    ids=["full", "floor"],
)
def test_a_full_disk_pauses_the_recordings_and_the_daemon_flies_on(
    tmp_path: Path, floor_mb: float, names: tuple[str, ...], reason: str
) -> None:
    port = free_port()
    with small_disk(tmp_path / "disk") as disk:
        files = {"telemetry": "cycle.mcap", "can_log": "bus.log"}
        recording = {name: str(disk / files[name]) for name in names}
        config = _config(tmp_path, port, {**recording, "min_free_mb": floor_mb})
        log = tmp_path / "daemon.log"
        proc = start_daemon(config, "--sim", log=log)
        events: list[dict] = []
        states: list[dict] = []
        try:
            connect(port, proc, timeout=90.0).close()  # up (a loaded host starts it slowly)
            with CdprClient(PREFIX, f"tcp/127.0.0.1:{port}", timeout=20.0) as client:
                subscriber = client.subscribe_events(lambda e: events.append(e))
                wait_status(client, "idle", 15.0)
                first = client.status()["recording"]
                assert first["telemetry"]["status"] == "recording", first
                client.enable()  # cycle telemetry is recorded while the robot is powered
                wait_status(client, "hold", 15.0)
                end = time.monotonic() + 90.0
                while not _paused(status := client.status()):
                    assert time.monotonic() < end, f"the recordings never paused: {status}"
                    assert proc.poll() is None, "the daemon exited"
                    time.sleep(0.2)
                answered = [client.status() for _ in range(10)]  # every one answered
                client.send_trajectory(_trajectory())
                wait_status(client, "tracking", 10.0)
                wait_status(client, "hold", 15.0)
                state_sub = client.subscribe_state(states.append)
                time.sleep(0.5)
                state_sub.undeclare()
                subscriber.undeclare()
                final = client.status()
        finally:
            finish(proc)  # SIGTERM: brake, finish the recordings, exit
    out = log.read_text()
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    assert set(status["recording"]) == set(names), status
    for name in names:
        report = status["recording"][name]
        assert report["status"] == "paused" and report["reason"].startswith(reason), report
        assert report["file"] is None, report
        # records that came while paused were dropped: by the flight's end (the status
        # that first says paused may come before the first record after the pause)
        assert final["recording"][name]["dropped"] > 0, final["recording"][name]
        said = [e for e in events if e.get("event") == "recording" and e["recording"] == name]
        assert said and said[-1]["status"] == "paused", events
        assert said[-1]["reason"].startswith(reason), said
    assert all(_paused(a) for a in answered), answered
    assert final["state"] == "hold" and final["fault"] is None, final
    assert states and all(_paused(s) for s in states), states[-1:]
    assert out.count("recording paused until there is room again") == len(names), out


def _trajectory() -> dict:
    quat = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "waypoints": [
            {"t": 0.0, "position": [0.0, 0.0, 1.25], "quaternion": quat},
            {"t": 1.0, "position": [0.05, 0.0, 1.28], "quaternion": quat},
        ]
    }
