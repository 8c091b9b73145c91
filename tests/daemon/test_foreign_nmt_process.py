"""Another node's NMT broadcast, with the daemon, the simulator and the intruder as
separate processes.  The simulator serves its bus over socketcand on 127.0.0.1 and logs
the platform's TRUE pose (--truth-log); the daemon (`cdprd run`, no --sim) drives it over
socketcand; this test, a third client on the bus, sends one NMT stop / enter
pre-operational / reset communication to every CiA 402 node (or Set_Axis_State(IDLE) to
every ODrive axis) while the robot holds or tracks a goto.  The daemon brakes, its
status confirms every drive's hold (drivers.cia402.hold_check: by SDO, in any NMT state;
an ODrive axis by heartbeat) and the platform stays within 2 mm for 5 s, where a drive
left in torque at its last command turns it by over 100 deg."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

from drivers.cia402 import codec
from drivers.cia402.codec import NmtCommand
from drivers.odrive import codec as odrive
from drivers.odrive.codec import AxisState
from tests.daemon_stack import DRIVER_CONFIGS
from tests.loopback import free_port
from tests.processes import (
    assert_still,
    connect,
    daemon_config,
    finish,
    serve_simulator,
    simulator_configs,
    start_daemon,
    truth,
    wait_status,
)

PREFIX = "cdpr/reference8"
ALLOWED = 2e-3  # m the true platform position may move once braked
WATCH = 5.0  # s watched: a drive left in torque drifts within 4 s

pytestmark = [pytest.mark.timeout(150), pytest.mark.slow]
COMMANDS = {
    "stop": NmtCommand.STOP,
    "pre-operational": NmtCommand.ENTER_PRE_OPERATIONAL,
    "reset-communication": NmtCommand.RESET_COMMUNICATION,
}


def wait_confirmed(client, timeout: float) -> dict:
    """The status once every drive confirmed the brake (AssertionError after `timeout`)."""
    end = time.monotonic() + timeout
    while not ((status := client.status())["brake"] or {}).get("confirmed"):
        assert time.monotonic() < end, f"brake never confirmed: {status}"
        time.sleep(0.05)
    return status


CASES = [
    *(("cia402", command, tracking) for command in COMMANDS for tracking in (False, True)),
    *(("odrive", "idle", tracking) for tracking in (False, True)),
]


def intrusion(protocol: str, command: str, nodes: list[int]) -> list[can.Message]:
    """The intruder's frames: one NMT broadcast, or Set_Axis_State(IDLE) to each axis."""
    if protocol == "cia402":
        return [codec.encode_nmt(COMMANDS[command], 0)]
    return [odrive.encode_set_axis_state(node, AxisState.IDLE) for node in nodes]


@pytest.mark.parametrize(
    ("protocol", "command", "tracking"),
    CASES,
    ids=[f"{p}-{c}-{'tracking' if t else 'holding'}" for p, c, t in CASES],
)
def test_another_node_s_command_ends_in_a_confirmed_hold(
    tmp_path: Path, protocol: str, command: str, tracking: bool
) -> None:
    zenoh_port = free_port()
    # an ODrive's watchdog counts from power-on: the simulator waits for the daemon
    watchdog = 1.0 if protocol == "odrive" else 0.2
    sim_config, data = simulator_configs(tmp_path, zenoh_port, DRIVER_CONFIGS[protocol], watchdog)
    truth_log = tmp_path / "truth.jsonl"
    sim, port, channel = serve_simulator(
        sim_config, "--duration", "100", "--truth-log", str(truth_log)
    )
    daemon = None
    events: list[dict] = []
    try:
        # ODrives stream their feedback over two TCP relays: late is not the point here
        patience = {"stale_cycles": 100} if protocol == "odrive" else {}
        config = daemon_config(tmp_path, data, port, channel, **patience)
        daemon = start_daemon(config, log=tmp_path / "daemon.log")
        with connect(zenoh_port, daemon) as client:
            wait_status(client, "idle", 10.0)
            subscriber = client.subscribe_events(events.append)
            client.enable()
            time.sleep(0.5)
            if tracking:
                home = truth(truth_log)[-1]["position"]
                reply = client.goto([home[0] + 0.1, home[1] + 0.05, home[2]])
                assert reply.get("accepted"), reply
                wait_status(client, "tracking", 10.0)
                time.sleep(0.3)
            intruder = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
            try:
                for frame in intrusion(protocol, command, data["drives"]["nodes"]):
                    intruder.send(frame)
            finally:
                intruder.shutdown()
            status = wait_status(client, "braked", 10.0)
            # the drives' report of the state (their heartbeat), their silence, or, when
            # idle axes drop the platform before the next heartbeat says so (one each
            # 100 ms), its weight as a wrench the model does not explain (seen on a fast
            # host, every run) or its fall itself: 20 mm, the tracking bound, takes 64 ms
            # (seen in a clean-clone CI run, the host busy with the other test worker)
            triggers = ("drive_fault", "stale_feedback", "external_wrench")
            if protocol == "odrive":
                triggers += ("tracking_error",)
            assert status["fault"]["trigger"] in triggers, status
            time.sleep(0.3)  # a brake at speed comes to rest
            start = truth(truth_log)[-1]
            status = wait_confirmed(client, 10.0)
            assert all(d["held"] for d in status["drives"]), status
            time.sleep(WATCH)
            assert client.status()["brake"]["confirmed"]
            subscriber.undeclare()
        finish(daemon)
    finally:
        if daemon is not None and daemon.poll() is None:
            finish(daemon)
        sim.terminate()
        sim.communicate(timeout=10)
    after = [t for t in truth(truth_log) if t["t"] >= start["t"]]
    assert len(after) > 30
    assert_still(after, start, ALLOWED)
    assert "brake_confirmed" in [e.get("event") for e in events], events
