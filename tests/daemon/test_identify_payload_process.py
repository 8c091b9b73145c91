"""`cdprd identify-payload --apply` against a running daemon over zenoh:
the simulator (a separate process, serving socketcand on 127.0.0.1) carries 2 kg the
robot file does not know; the daemon (`cdprd run`, its core and companion processes)
drives it, its online estimate learning the payload while it holds; the command line asks
for the static estimate, which the companion makes by holding five poses, and the core
applies it; `cdprd payload --freeze` then freezes the estimate."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.daemon.test_daemon_payload import PAYLOAD, TRUE_COM, TRUE_MASS
from tests.loopback import free_port
from tests.processes import (
    PREFIX,
    ROOT,
    connect,
    daemon_config,
    finish,
    serve_simulator,
    simulator_configs,
    start_daemon,
    wait_status,
)

pytestmark = [pytest.mark.timeout(150), pytest.mark.slow, pytest.mark.host_timing]


def test_identify_payload_from_the_command_line(tmp_path: Path) -> None:
    zenoh_port = free_port()
    sim_config, data = simulator_configs(tmp_path, zenoh_port)
    data["sim"]["plant"]["mismatch"] = {"payload": PAYLOAD}
    sim_config.write_text(json.dumps(data))  # YAML is a superset of JSON
    sim, port, channel = serve_simulator(sim_config, "--duration", "140")
    daemon = None
    try:
        config = daemon_config(tmp_path, data, port, channel)
        daemon = start_daemon(config, log=tmp_path / "daemon.log")
        with connect(zenoh_port, daemon) as client:
            wait_status(client, "idle", 10.0)
            client.enable()
            wait_status(client, "hold", 10.0)
            time.sleep(2.0)  # the online estimate takes the payload in
            result = _cdprd(zenoh_port, "identify-payload", "--apply")
            payload = client.request("payload")
            frozen = _cdprd(zenoh_port, "payload", "--freeze", "--lease", "30")
            status = client.status()
            unleased = _cdprd_fails(zenoh_port, "observer", "--release", "--lease", "5")
            # the lease is the freezing command's: another releases it only with its id
            kept = _cdprd_fails(zenoh_port, "payload", "--unfreeze")
            ident = frozen["lease_id"]
            released = _cdprd(zenoh_port, "payload", "--unfreeze", "--lease-id", ident)
        finish(daemon)
    finally:
        if daemon is not None and daemon.poll() is None:
            finish(daemon)
        sim.terminate()
        sim.communicate(timeout=10)
    assert status["state"] == "hold" and status["fault"] is None, status
    assert result["poses"] == 5 and result["applied"] is True, result
    assert result["mass"] == pytest.approx(TRUE_MASS, rel=0.01), result
    assert np.abs(np.subtract(result["center_of_mass"], TRUE_COM)).max() < 3e-3, result
    # applied, and the online estimate since agrees with it
    assert payload["mass"] == pytest.approx(TRUE_MASS, rel=0.01) and payload["frozen"] is False
    assert frozen["frozen"] is True and frozen["mass"] == pytest.approx(TRUE_MASS, rel=0.01)
    assert 0.0 < status["leases"]["payload"] <= 30.0, status  # --lease: on a lease
    assert "lease" in unleased  # a lease without a hold: refused, naming the key
    assert "payload: refused (not_owner)" in kept and "with its lease_id" in kept, kept
    assert released["frozen"] is False and "lease_id" not in released, released


def _cdprd(port: int, *command: str) -> dict:
    """What `cdprd COMMAND` prints, run against the daemon on zenoh `port`."""
    cli = _run(port, *command, "--json")
    assert cli.returncode == 0, cli.stderr
    return json.loads(cli.stdout)


def _cdprd_fails(port: int, *command: str) -> str:
    """What `cdprd COMMAND` says on stderr when the daemon refuses it (exit code 1)."""
    cli = _run(port, *command)
    assert cli.returncode == 1, (cli.stdout, cli.stderr)
    return cli.stderr


def _run(port: int, *command: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable, "-m", "daemon.cli", *command,
            "--prefix", PREFIX, "--connect", f"tcp/127.0.0.1:{port}",
        ],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
