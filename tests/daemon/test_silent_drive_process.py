"""One silent drive must not cost the operator the command channel (DESIGN §16).

The simulator serves its bus over socketcand (`python -m sim_bus --fault-input`); the
daemon (`cdprd run`, no --sim) drives it with safety.feedback_deadline 0.9, so that every
cycle whose feedback never comes waits 90 % of the period for it.  While it holds, one
drive goes silent (typed into the simulator): the daemon brakes on the stale feedback,
and then, with the drive still silent, every status query is answered, a reset is
answered (refused, naming what persists), and the companion (zenoh) is never killed as
unresponsive: the calls and its liveness messages are served every cycle whatever the
feedback does.  Counts, not times: a loaded host only makes the replies slower.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from daemon.interface.client import CdprClient, RequestError, UnreachableError
from tests.loopback import free_port
from tests.processes import (
    connect,
    daemon_config,
    finish,
    serve_simulator,
    simulator_configs,
    start_daemon,
    wait_status,
)

QUERIES = 10

pytestmark = [pytest.mark.timeout(180), pytest.mark.slow]


def _answered(client: CdprClient, command: str) -> dict | RequestError | None:
    """The reply to `command`: its result, the refusal (answered too), or None."""
    try:
        return client.request(command)
    except RequestError as refused:
        return refused
    except UnreachableError:
        return None


def test_one_silent_drive_at_a_long_feedback_deadline_leaves_the_command_channel_served(
    tmp_path: Path,
) -> None:
    zenoh = free_port()
    sim_config, data = simulator_configs(tmp_path, zenoh)
    sim, port, channel = serve_simulator(sim_config, "--fault-input", "--duration", "150")
    daemon = None
    try:
        config = daemon_config(tmp_path, data, port, channel, feedback_deadline=0.9)
        log = tmp_path / "daemon.log"
        daemon = start_daemon(config, log=log)
        with connect(zenoh, daemon) as client:
            wait_status(client, "idle", 15.0)
            client.enable()
            wait_status(client, "hold", 10.0)
        sim.stdin.write("silent:3\n")
        sim.stdin.flush()
        with CdprClient("cdpr/reference8", f"tcp/127.0.0.1:{zenoh}", timeout=10.0) as client:
            braked = wait_status(client, "braked", 20.0)
            replies = [_answered(client, "status") for _ in range(QUERIES)]
            reset = _answered(client, "reset")
        assert daemon.poll() is None, "the daemon exited"
        output = finish(daemon)
    finally:
        if daemon is not None and daemon.poll() is None:
            finish(daemon)
        sim.terminate()
        sim.communicate(timeout=10)
    text = log.read_text()
    answered = [r for r in replies if isinstance(r, dict)]
    assert len(answered) == QUERIES, f"{len(answered)} of {QUERIES} status queries answered"
    assert all(r["state"] == "braked" for r in answered), answered
    assert braked["fault"] is not None, braked
    assert reset is not None, "the reset was not answered"
    if isinstance(reset, RequestError):  # refused: the silent drive's feedback is stale
        assert reset.code == "invalid_state" and "persist" in reset.reason, reset.reply
    assert "killing it" not in text, text + str(output)
    assert "companion exited" not in text, text
