"""Failure semantics between the real-time core and its companion process, as
separate processes: the simulator serving its bus over socketcand and
logging the platform's TRUE pose (--truth-log), and `cdprd run` driving it.

- the companion killed: the core restarts it, the robot stays held, zenoh answers again;
- the companion hung (SIGSTOP): the core brakes a moving robot after
  safety.companion_lost, kills the silent companion after safety.companion_hang and
  starts a new one, which reports the brake;
- the core killed: the drives' watchdogs hold the platform, the companion exits on its
  own, and a new daemon (what systemd would restart) comes up held, naming the drives'
  watchdog faults, and a reset makes it IDLE, all without moving the platform;
- the companion killed while the observer is held on a lease: the new one lets go
  when the time the lease had left runs out, or at once if it ran out meanwhile;
- the installed code changed under the running daemon (an upgrade): the companion the
  core starts next runs other code, says so, and the daemon brakes and exits (3) for
  systemd to start it again on the new code.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import psutil
import pytest

from daemon.interface.client import CdprClient, RequestError
from daemon.process import wire
from tests.loopback import free_port
from tests.processes import (
    ROOT,
    connect,
    daemon_config,
    finish,
    serve_simulator,
    simulator_configs,
    start_daemon,
    truth,
    wait_status,
)

ALLOWED = 2e-3  # m the true platform may move
# with the core dead the drives apply its last torque until their watchdog fires (0.2 s
# in simulator_configs, patient for the TCP relays), then hold: a little more drift
ALLOWED_DEAD = 5e-3

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


class Rig:
    """The simulator process, its truth log and the daemon's zenoh port."""

    def __init__(self, tmp_path: Path, sim: subprocess.Popen, config: Path, zenoh: int) -> None:
        self.tmp_path, self.sim, self.config, self.zenoh = tmp_path, sim, config, zenoh
        self.truth_log = tmp_path / "truth.jsonl"

    def start_daemon(self, name: str) -> subprocess.Popen:
        return start_daemon(self.config, log=self.tmp_path / f"{name}.log")

    def log(self, name: str) -> str:
        return (self.tmp_path / f"{name}.log").read_text()

    def moved_since(self, t: float) -> float:
        """The farthest the true platform got from where it was at simulator time t."""
        records = [r for r in truth(self.truth_log) if r["t"] >= t]
        assert len(records) > 10, "the truth log stopped"
        p0 = np.array(records[0]["position"])
        return max(float(np.linalg.norm(np.array(r["position"]) - p0)) for r in records)

    def now(self) -> float:
        return truth(self.truth_log)[-1]["t"]

    def holding(self, daemon: subprocess.Popen) -> float:
        """Enable the daemon once idle and let it hold; the simulator time then."""
        with connect(self.zenoh, daemon) as client:
            wait_status(client, "idle", 10.0)
            client.enable()
            wait_status(client, "hold", 5.0)
        time.sleep(0.3)
        return self.now()


@contextmanager
def rig(tmp_path: Path, **safety: float) -> Iterator[Rig]:
    zenoh = free_port()
    sim_config, data = simulator_configs(tmp_path, zenoh)
    options = ["--duration", "100", "--truth-log", str(tmp_path / "truth.jsonl")]
    sim, port, channel = serve_simulator(sim_config, *options)
    try:
        yield Rig(tmp_path, sim, daemon_config(tmp_path, data, port, channel, **safety), zenoh)
    finally:
        sim.terminate()
        sim.communicate(timeout=10)


def companion_of(daemon: subprocess.Popen, timeout: float = 30.0, not_pid: int = 0) -> int:
    """The pid of the daemon's companion process (other than `not_pid`)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        for child in psutil.Process(daemon.pid).children():
            try:
                command = " ".join(child.cmdline())
            except psutil.Error:  # exited (a zombie until the core reaps it)
                continue
            if "daemon.process.companion" in command and child.pid != not_pid:
                return child.pid
        time.sleep(0.05)
    raise AssertionError("no companion process")


def test_a_killed_companion_is_restarted_and_the_robot_stays_held(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        daemon = r.start_daemon("daemon")
        try:
            since = r.holding(daemon)
            first = companion_of(daemon)
            psutil.Process(first).kill()
            second = companion_of(daemon, not_pid=first)
            with connect(r.zenoh, daemon) as client:
                status = client.status()  # a query answered by the new companion
            time.sleep(0.5)
            moved = r.moved_since(since)
            assert daemon.poll() is None, "the core exited with its companion"
        finally:
            finish(daemon)
    assert second != first
    assert status["state"] == "hold" and status["fault"] is None, status
    assert moved < ALLOWED, f"the platform moved {moved * 1e3:.2f} mm"
    log = r.log("daemon")
    assert "the companion exited with code -9: restarting it" in log, log


def test_a_hung_companion_brakes_a_moving_robot_and_is_replaced(tmp_path: Path) -> None:
    with rig(tmp_path, companion_lost=0.5, companion_hang=1.5) as r:
        daemon = r.start_daemon("daemon")
        try:
            since = r.holding(daemon)
            first = companion_of(daemon)
            psutil.Process(first).send_signal(signal.SIGSTOP)
            companion_of(daemon, not_pid=first)  # killed after 1.5 s, then restarted
            with connect(r.zenoh, daemon) as client:
                status = wait_status(client, "braked", 10.0)
            time.sleep(0.5)
            moved = r.moved_since(since)
        finally:
            finish(daemon)
    assert status["fault"]["trigger"] == "companion_lost", status
    assert "safety.companion_lost 0.5 s" in status["fault"]["message"], status
    assert moved < ALLOWED, f"the platform moved {moved * 1e3:.2f} mm"
    log = r.log("daemon")
    assert "has been silent for" in log and log.count("killing it") == 1, log


def test_a_killed_core_leaves_the_drives_holding_and_a_restart_comes_up_held(
    tmp_path: Path,
) -> None:
    with rig(tmp_path) as r:
        daemon = r.start_daemon("daemon")
        restarted = None
        try:
            since = r.holding(daemon)
            companion = psutil.Process(companion_of(daemon))
            daemon.kill()  # SIGKILL: no brake frame, no goodbye
            daemon.wait(10)
            companion.wait(10)  # it notices the core is gone and exits (psutil.TimeoutExpired)
            time.sleep(1.0)  # the drives' watchdogs fired and hold
            moved_dead = r.moved_since(since)
            since = r.now()
            restarted = r.start_daemon("restarted")
            with connect(r.zenoh, restarted) as client:
                # the drives' watchdog (the host's heartbeat, 0x1016) quick-stopped them:
                # QUICK STOP ACTIVE, holding, taken as they are
                status = wait_status(client, "idle", 15.0)
            time.sleep(0.5)
            moved_restart = r.moved_since(since)
        finally:
            if restarted is not None:
                finish(restarted)
            if daemon.poll() is None:
                finish(daemon)
    assert moved_dead < ALLOWED_DEAD, f"the platform moved {moved_dead * 1e3:.2f} mm (core dead)"
    assert status["fault"] is None, status
    assert [d["state"] for d in status["drives"]] == ["holding"] * 8, status
    assert moved_restart < ALLOWED, f"the platform moved {moved_restart * 1e3:.2f} mm"


RESTART_LEASE = 20.0  # s: outlasts a companion's restart (seconds) on a loaded host


def _let_go(client: CdprClient, bound: float) -> dict:
    """The status once the observer is back in the loop (AssertionError after `bound` s)."""
    end = time.monotonic() + bound
    while client.observer()["held"]:
        assert time.monotonic() < end, f"still held: {client.status()['leases']}"
        time.sleep(0.1)
    return client.status()


def test_a_restarted_companion_lets_go_within_the_lease_left(tmp_path: Path) -> None:
    """The observer held on a lease, the companion killed (kill -9): the new one shows the
    lease again with less time left than before the kill, still its holder's (a release
    without its id, or with another, is refused naming the holder), and lets go when it
    runs out (warning); the robot keeps holding."""
    with rig(tmp_path) as r:
        daemon = r.start_daemon("daemon")
        try:
            r.holding(daemon)
            with connect(r.zenoh, daemon) as client:
                taken = client.observer(True, lease=RESTART_LEASE)
                assert taken["held"] is True
                before = client.status()["leases"]["observer"]
                holder = client.name
            first = companion_of(daemon)
            psutil.Process(first).kill()
            companion_of(daemon, not_pid=first)
            with connect(r.zenoh, daemon) as client:
                held = client.observer()["held"]
                restarted = client.status()  # the new companion's
                refusals = []
                for lease_id in (None, "0" * 24):
                    with pytest.raises(RequestError) as refused:
                        client.observer(False, lease_id=lease_id)
                    refusals.append(refused.value)
                released = _let_go(client, 3 * RESTART_LEASE)
        finally:
            finish(daemon)
    assert held is True
    assert all(r.code == "not_owner" and f"{holder}'s" in r.reason for r in refusals), refusals
    assert "is not that lease's" in refusals[1].reason, refusals  # the id is the same one
    assert 0.0 < restarted["leases"]["observer"] < before <= RESTART_LEASE, (before, restarted)
    assert restarted["leases"]["payload"] is None
    assert released["leases"] == {"payload": None, "observer": None}, released
    assert released["state"] == "hold" and released["fault"] is None, released
    log = r.log("daemon")
    assert "the companion exited with code -9: restarting it" in log, log
    assert "the external wrench observer's hold runs on" in log, log
    assert "hold lapsed: not renewed within its lease of 20 s" in log, log
    assert f"(held by {holder})" in log and taken["lease_id"] not in log, log


def test_a_lease_that_ran_out_while_the_companion_was_down_lapses_at_once(
    tmp_path: Path,
) -> None:
    """The observer held on a 0.5 s lease, the companion stopped (SIGSTOP: it cannot let
    go) for longer than that, then killed: the new one lets go as it starts."""
    with rig(tmp_path) as r:
        daemon = r.start_daemon("daemon")
        try:
            r.holding(daemon)
            with connect(r.zenoh, daemon) as client:
                assert client.observer(True, lease=0.5)["held"] is True
            first = psutil.Process(companion_of(daemon))
            first.send_signal(signal.SIGSTOP)
            time.sleep(1.0)  # the lease runs out with no companion to time it
            with contextlib.suppress(psutil.NoSuchProcess):  # the core killed it (silent)
                first.kill()
            companion_of(daemon, not_pid=first.pid)
            with connect(r.zenoh, daemon) as client:
                released = _let_go(client, 10.0)
        finally:
            finish(daemon)
    assert released["leases"] == {"payload": None, "observer": None}, released
    assert released["state"] == "hold" and released["fault"] is None, released
    log = r.log("daemon")
    assert "hold runs on: 0 s left of its lease of 0.5 s" in log, log
    assert "hold lapsed: not renewed within its lease of 0.5 s" in log, log


def test_code_upgraded_under_the_running_daemon_stops_it_when_the_companion_restarts(
    tmp_path: Path,
) -> None:
    """`cdprd run --sim` from a copy of the packages; while it holds, a source file of
    the copy changes (as `pip install -U` would) and the companion is killed: the new
    companion imports the changed code, refuses the core's hello naming both
    fingerprints, and the core brakes and exits with wire.OTHER_CODE."""
    tree = tmp_path / "installed"
    for name in (*wire.PACKAGES, "config"):  # config/can: the drives' EDS
        shutil.copytree(ROOT / name, tree / name, ignore=shutil.ignore_patterns("__pycache__"))
    zenoh = free_port()
    config, _data = simulator_configs(tmp_path, zenoh)
    log = tmp_path / "daemon.log"
    daemon = start_daemon(config, "--sim", log=log, cwd=tree)
    try:
        # the copy's numba cache is cold: the companion compiles the validation's kernels
        # before it answers (22 s on this host, alone)
        with connect(zenoh, daemon, timeout=120.0) as client:
            wait_status(client, "idle", 10.0)
            client.enable()
            wait_status(client, "hold", 5.0)
        first = companion_of(daemon)
        with (tree / "daemon" / "process" / "wire.py").open("a") as source:
            source.write("# upgraded\n")
        psutil.Process(first).kill()
        assert daemon.wait(timeout=60) == wire.OTHER_CODE
    finally:
        finish(daemon)
    text = log.read_text()
    assert "is not the core's" in text and "restart it" in text
    assert "the installed cdprd changed under the running service: stopping" in text
    assert "BRAKE [companion_lost]" in text
