"""Starting the simulator processes tests need (and daemons driving them over
socketcand), and stopping the daemon processes they start the way systemd or an
operator would."""

from __future__ import annotations

import contextlib
import json
import math
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml

from daemon.cli.simulated import SIMULATOR_PRIORITY, realtime_child
from daemon.interface.client import CdprClient, UnreachableError

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/reference8"
ANNOUNCED = re.compile(r"serving socketcand on 127\.0\.0\.1:(\d+) channel (\S+)")


def serve_simulator(
    config: Path,
    *options: str,
    stderr: int = subprocess.DEVNULL,
    priority: int = SIMULATOR_PRIORITY,
) -> tuple[subprocess.Popen, int, str]:
    """`python -m sim_bus --config CONFIG OPTIONS` serving its bus over socketcand on a
    free loopback port, text pipes on stdin and stdout, at SCHED_FIFO `priority` where
    permitted: (process, port, channel) once it announced them (log lines may come
    first)."""
    args = [sys.executable, "-m", "sim_bus", "--config", str(config), *options]
    proc = subprocess.Popen(
        [*args, "--serve-socketcand", "127.0.0.1:0"],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
        preexec_fn=realtime_child(priority),
    )
    line = ""
    for _ in range(20):
        line = proc.stdout.readline()
        match = ANNOUNCED.search(line)
        if match:
            return proc, int(match.group(1)), match.group(2)
        if not line:
            break
    proc.kill()
    proc.communicate()
    raise AssertionError(f"the simulator announced no socketcand endpoint: {line!r}")


def start_daemon(
    config: Path,
    *options: str,
    log: Path | None = None,
    cwd: Path = ROOT,
    env: dict[str, str] | None = None,
) -> subprocess.Popen:
    """`cdprd run --config CONFIG OPTIONS` as its own process, run from `cwd` (whose
    packages it imports), in `env` (default: this process's): its output (stdout and
    stderr) to the file `log`, else to a text pipe."""
    argv = [sys.executable, "-m", "daemon.cli", "run", "--config", str(config), *options]
    if log is None:
        return subprocess.Popen(
            argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
    with log.open("w") as out:  # the child keeps its own descriptor open
        return subprocess.Popen(argv, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)


def cdprd(
    *args: str, timeout: float = 120.0, cwd: Path = ROOT, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """`python -m daemon.cli ARGS` run from `cwd` (default this checkout) in `env`
    (default: this process's), to its end: its exit code, stdout and stderr."""
    command = [sys.executable, "-m", "daemon.cli", *args]
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def stop_impatiently(proc: subprocess.Popen, timeout: float = 15.0) -> None:
    """SIGTERM every 20 ms until the process exits, as an impatient operator would."""
    end = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < end:
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.02)


def finish(proc: subprocess.Popen, terminate: bool = True, timeout: float = 15.0) -> str:
    """SIGTERM (with `terminate`, if still running), then the process's output once it
    exits; killed if it hangs longer than `timeout`."""
    if terminate and proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


def patient_watchdogs(data: dict, timeout: float = 0.2) -> None:
    """Config `data` with patient drive watchdogs for a loaded test machine (drive-side
    timeouts and the drives' consumer of the host heartbeat `timeout`, the host's consumer
    of theirs 1 s), so that only what a test does decides how its run ends.  A dead
    daemon then goes unnoticed for `timeout`: the drift the config accepts is raised
    with it (safety.max_watchdog_drift, not what these tests are about)."""
    data["drives"].update(watchdog_timeout=timeout, heartbeat_timeout=1.0)
    data.setdefault("safety", {})["max_watchdog_drift"] = 10.0


def simulator_configs(
    tmp_path: Path, zenoh_port: int, config: Path = CONFIG, watchdog: float = 0.2
) -> tuple[Path, dict]:
    """The reference8 CiA 402 config (or another example `config`) for `python -m
    sim_bus` (its file, and its data for daemon_config), zenoh on `zenoh_port`, drive
    watchdogs `watchdog` (patient_watchdogs)."""
    data = yaml.safe_load(config.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{zenoh_port}"]
    patient_watchdogs(data, watchdog)  # three processes and TCP relays on a busy 2-CPU host
    sim = tmp_path / "sim.yaml"
    sim.write_text(yaml.safe_dump(data))
    return sim, data


def socketcand_can(port: int, channel: str) -> dict:
    """The `can:` section for the simulator's socketcand bus on loopback `port`."""
    return {
        "interface": "socketcand",
        "channel": channel,
        "options": {"host": "127.0.0.1", "port": port},
    }


def daemon_config(tmp_path: Path, data: dict, port: int, channel: str, **safety: float) -> Path:
    """The daemon's config file: `data` (simulator_configs) on the simulator's socketcand
    bus at `port`, `channel`, with `safety` settings on top."""
    data = dict(data)
    data["can"] = socketcand_can(port, channel)
    # late feedback is not the point
    data["safety"] = {**data["safety"], "stale_cycles": 25, **safety}
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def truth(path: Path) -> list[dict]:
    """The simulator's --truth-log records so far."""
    lines = path.read_text().splitlines()
    return [json.loads(line) for line in lines[:-1]]  # the last may be half written


def assert_still(
    records: list[dict], start: dict, moved_max: float = 2e-3, turned_max: float = 5e-3
) -> None:
    """The true platform in the --truth-log `records` moved at most `moved_max` (m) and
    turned at most `turned_max` (rad) from the record `start`."""
    p0 = np.array(start["position"])
    q0 = np.array(list(start["quaternion"].values()))
    moved = max(np.linalg.norm(np.array(t["position"]) - p0) for t in records)
    turned = max(
        2 * math.acos(min(1.0, abs(float(np.array(list(t["quaternion"].values())) @ q0))))
        for t in records
    )
    assert moved < moved_max, f"the platform moved {moved * 1e3:.2f} mm"
    assert turned < turned_max, f"the platform turned {math.degrees(turned):.3f} deg"


def connect(port: int, proc: subprocess.Popen, timeout: float = 30.0) -> CdprClient:
    """A client once the daemon answers a status query on zenoh (it starts in a second
    or two)."""
    end = time.monotonic() + timeout
    while True:
        assert proc.poll() is None, f"the daemon exited early: {finish(proc, False)}"
        try:
            client = CdprClient(PREFIX, f"tcp/127.0.0.1:{port}", timeout=5.0)
        except UnreachableError:
            client = None
        if client is not None:
            try:
                client.status()
                return client
            except UnreachableError:
                client.close()
        assert time.monotonic() < end, "the daemon never answered on zenoh"
        time.sleep(0.2)


def wait_status(client: CdprClient, state: str, timeout: float) -> dict:
    """The status once the safety state is `state` (AssertionError after `timeout` s)."""
    end = time.monotonic() + timeout
    while (status := client.status())["state"] != state:
        assert time.monotonic() < end, f"never {state}: {status}"
        time.sleep(0.05)
    return status


@contextlib.contextmanager
def enabled_sim(config: Path, port: int) -> Iterator[subprocess.Popen]:
    """`cdprd run --sim` on `config` (zenoh on `port`), enabled and holding; stopped on
    leaving."""
    proc = start_daemon(config, "--sim")
    try:
        with connect(port, proc) as client:
            wait_status(client, "idle", 30.0)
            client.enable()
            wait_status(client, "hold", 10.0)
        yield proc
    finally:
        finish(proc)
