"""A forged length synchronised to the SYNC, and a glitching encoder, with the daemon,
the simulator and the attacker as separate processes.  The simulator
serves its bus over socketcand on 127.0.0.1 and logs the platform's TRUE pose
(--truth-log); the daemon (`cdprd run`, no --sim) drives it over socketcand and holds.
Forged: this test, a third client on the same bus, answers every SYNC it sees with a
TPDO1 + TPDO2 claiming 4.1 m for cable 0 (really ~2.33 m) until the daemon braked and
half a second longer, each time right after the drive's own answer (on a quiet host
the forgery then always came second, was dropped, and never braked: CI).  Over the TCP
relays a late drive answer can still let the forgery come first; either way one SYNC
got two answers 1.8 m apart, and the daemon brakes every time, naming the forged length
(of the answer it took, or of the one it dropped).  Glitch: typed
into the simulator (--fault-input), drive 0 reports its length 0.1 m off in its own
answers to every SYNC.  The daemon brakes naming the drive (zenoh event, status, log)
and the platform stays within 2 mm of where it was (on main the forgery moves it
~210 mm)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import can
import pytest
import yaml

from daemon.interface.client import CdprClient
from drivers.cia402 import codec
from drivers.cia402.statemachine import MODE_CST
from drivers.config import parse_drives
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

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/reference8"
FORGED = 4.1  # m claimed for cable 0 (node 1)
SYNCS = 5000  # the attacker answers at most this many SYNCs (10 s at 500 Hz)
ALLOWED = 2e-3  # m the true platform position may move

pytestmark = [pytest.mark.timeout(120), pytest.mark.slow]


class Attacker(threading.Thread):
    """A socketcand client on the simulator's bus that answers every SYNC it sees, right
    after node 1's own answer (its TPDO2), with a forged TPDO1 + TPDO2 of node 1 (the
    statusword copied from the drive's own TPDO1), until `stop` is set or it answered
    SYNCS of them."""

    def __init__(self, port: int, channel: str, position: int) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
        self.position = position
        self.answered = 0
        self.stop = threading.Event()

    def run(self) -> None:
        try:
            self._answer()
        finally:
            self.bus.shutdown()

    def _answer(self) -> None:
        bus, position = self.bus, self.position
        statusword, mode, synced = None, MODE_CST, False
        end = time.monotonic() + 20.0
        while not self.stop.is_set() and self.answered < SYNCS and time.monotonic() < end:
            msg = bus.recv(0.1)
            if msg is None:
                continue
            can_id = msg.arbitration_id
            if can_id == codec.SYNC_ID:
                synced = True
            elif can_id == codec.TPDO1_BASE + 1 and statusword is None:
                statusword, _, mode = codec.decode_tpdo1(can_id, msg.data)
            elif can_id == codec.TPDO2_BASE + 1 and synced and statusword is not None:
                bus.send(codec.encode_tpdo1(1, statusword, position, mode))
                bus.send(codec.encode_tpdo2(1, 0))
                self.answered += 1
                synced = False


def _forge_until_braked(client: CdprClient, data: dict, port: int, channel: str) -> dict:
    """Answer every SYNC with a forged length until the daemon braked and 0.5 s longer;
    the daemon's status once braked."""
    drives = parse_drives(data["drives"])
    robot_file = yaml.safe_load(Path(data["robot"]).read_text())
    scaling = drives.scalings([robot_file["actuator"]["drum_radius"]] * 8)[0]
    attacker = Attacker(port, channel, round(scaling.position(FORGED)))
    attacker.start()
    try:
        status = wait_status(client, "braked", 10.0)
        answered = attacker.answered
        time.sleep(0.5)  # braked, the attack goes on: the brake must not follow it
    finally:
        attacker.stop.set()
        attacker.join(5.0)
    assert attacker.answered > answered + 100
    return status


@pytest.mark.parametrize("attack", ["forged", "glitch"])
def test_a_forged_or_glitching_length_brakes_naming_the_drive_and_nothing_moves(
    tmp_path: Path, attack: str
) -> None:
    zenoh_port = free_port()
    sim_config, data = simulator_configs(tmp_path, zenoh_port)
    truth_log = tmp_path / "truth.jsonl"
    options = ["--duration", "100", "--truth-log", str(truth_log)]
    options += ["--fault-input"] if attack == "glitch" else []
    sim, port, channel = serve_simulator(sim_config, *options)
    daemon = None
    try:
        config = daemon_config(tmp_path, data, port, channel)
        daemon = start_daemon(config, log=tmp_path / "daemon.log")
        events: list[dict] = []
        with connect(zenoh_port, daemon) as client:
            wait_status(client, "idle", 10.0)
            subscriber = client.subscribe_events(events.append)
            client.enable()
            time.sleep(0.5)
            start = truth(truth_log)[-1]
            if attack == "forged":
                status = _forge_until_braked(client, data, port, channel)
            else:
                sim.stdin.write("glitch:0\n")
                sim.stdin.flush()
                status = wait_status(client, "braked", 10.0)
                time.sleep(0.5)  # braked, the glitch goes on: the brake must not follow it
            time.sleep(0.3)  # and after it
            subscriber.undeclare()
        daemon_out = finish(daemon)
    finally:
        if daemon is not None and daemon.poll() is None:
            finish(daemon)
        sim.terminate()
        sim.communicate(timeout=10)  # closes its stdin too
    after = [t for t in truth(truth_log) if t["t"] >= start["t"]]
    assert len(after) > 30  # the whole attack and what followed
    assert_still(after, start, ALLOWED)
    fault = status["fault"]
    assert fault["trigger"] == "implausible_feedback", status
    claimed = "4.1000 m" if attack == "forged" else ""
    assert fault["message"].startswith(f"drive 0 (node 1): length {claimed}"), fault
    brakes = [e for e in events if e.get("event") == "brake"]
    assert brakes and brakes[0]["message"] == fault["message"], events
    log = (tmp_path / "daemon.log").read_text()
    assert "BRAKE [implausible_feedback] drive 0 (node 1)" in log, log + daemon_out
