"""`python -m sim_bus` as its own process, serving its bus in the socketcand protocol: a
python-can client in this process hears the virtual CiA 402 drives boot, maps their
feedback PDO, starts them, sends SYNC and decodes their feedback with the project's
codec; a device fault given on the command line arrives as an EMCY."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
import yaml

from cdpr import Robot
from drivers.cia402 import codec
from drivers.config import parse_drives
from tests.processes import serve_simulator

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"


def _frames(bus: can.BusABC, seconds: float) -> list[can.Message]:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        msg = bus.recv(0.05)
        if msg is not None:
            out.append(msg)
    return out


def _answering_sync(bus: can.BusABC) -> set[int]:
    """The nodes whose TPDO1 answers one SYNC (within half a second)."""
    bus.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
    return {
        m.arbitration_id - 0x180 for m in _frames(bus, 0.5) if 0x181 <= m.arbitration_id <= 0x188
    }


def _configure(bus: can.BusABC, node: int, layout: codec.PdoLayout) -> None:
    """Map `layout` in drive `node` by SDO (expedited writes, each answered)."""
    od = codec.load_eds(codec.EDS_PATH, node)
    for index, sub, value in layout.mapping_procedure(node):
        data = codec.od_variable(od, index, sub).encode_raw(value)
        bus.send(codec.encode_sdo_download_request(node, index, sub, data))
        answers = (bus.recv(5.0) for _ in range(100))  # other nodes may talk meanwhile
        answer = next((m for m in answers if m is None or m.arbitration_id == 0x580 + node), None)
        assert answer is not None, f"node {node}: no answer to 0x{index:04X}:{sub:02X}"
        sdo = codec.decode_sdo_response(answer.arbitration_id, answer.data)
        assert sdo.kind is codec.SdoKind.DOWNLOAD, f"node {node}: 0x{index:04X}:{sub:02X}"


@pytest.mark.timeout(60)
def test_simulator_process_serves_its_drives_over_socketcand() -> None:
    args = [sys.executable, "-m", "sim_bus", "--config", str(CONFIG)]
    args += ["--serve-socketcand", "127.0.0.1:0", "--duration", "20", "--fault", "drive:2@3.0"]
    args += ["--report-every", "1"]
    proc = subprocess.Popen(
        args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        line = proc.stdout.readline()
        match = re.search(r"serving socketcand on 127\.0\.0\.1:(\d+) channel (\S+)", line)
        assert match, line + proc.stderr.read()
        port, channel = int(match.group(1)), match.group(2)
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
        try:
            # NMT reset communication: every node answers with its boot-up message
            bus.send(can.Message(arbitration_id=0x000, data=[0x82, 0], is_extended_id=False))
            heard = {m.arbitration_id for m in _frames(bus, 0.5)}
            assert {0x700 + n for n in range(1, 9)} <= heard

            # a strict drive ships with TPDO1 = statusword, event-driven: map the feedback
            for node in range(1, 9):
                _configure(bus, node, codec.TPDO1)
            bus.send(can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False))
            time.sleep(0.1)
            bus.send(can.Message(arbitration_id=0x080, data=[], is_extended_id=False))
            tpdo1 = {
                m.arbitration_id - 0x180: m
                for m in _frames(bus, 0.5)
                if 0x181 <= m.arbitration_id <= 0x188
            }
            assert sorted(tpdo1) == list(range(1, 9))
            robot = Robot.from_yaml(ROOT / "config" / "robots" / "reference8.yaml")
            drives = parse_drives(yaml.safe_load(CONFIG.read_text())["drives"], "drives")
            scaling = drives.scalings([a.drum_radius for a in robot.actuators])[0]
            _, position, _ = codec.decode_tpdo1(0x181, tpdo1[1].data)
            home = robot.cable_lengths(robot.home)[0]
            assert abs(scaling.length(position) - home) < 0.01  # the cable, in metres

            emcy = [m for m in _frames(bus, 3.5) if m.arbitration_id == 0x083]
            assert emcy, "no EMCY from node 3 after the injected drive fault"
            assert codec.decode_emcy(0x083, emcy[0].data)[0] == 0x2310
        finally:
            bus.shutdown()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
    out, err = proc.communicate()
    assert proc.returncode == 0, err
    # the status line, printed every second meanwhile
    assert re.search(r"t=\d+\.\d s bus load \d+\.\d% \(\d+ frames/s at \d+ bit/s\)", out), out


@pytest.mark.timeout(60)
def test_faults_typed_on_standard_input_are_injected_at_once() -> None:
    proc, port, channel = serve_simulator(
        CONFIG, "--fault-input", "--duration", "20", stderr=subprocess.PIPE
    )
    try:
        bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
        try:
            # a strict drive ships with TPDO1 = statusword, event-driven: map the feedback
            for node in range(1, 9):
                _configure(bus, node, codec.TPDO1)
            bus.send(can.Message(arbitration_id=0x000, data=[0x01, 0], is_extended_id=False))
            proc.stdin.write("drive:9\nnonsense\n")
            proc.stdin.flush()
            assert not [m for m in _frames(bus, 1.0) if 0x081 <= m.arbitration_id <= 0x088]
            proc.stdin.write("drive:4\n")  # cable 4 is node 5
            proc.stdin.flush()
            emcy = [m for m in _frames(bus, 2.0) if 0x081 <= m.arbitration_id <= 0x088]
            assert [m.arbitration_id for m in emcy] == [0x085]
            assert _answering_sync(bus) == set(range(1, 9))
            proc.stdin.write("silent:2\n")  # node 3 neither hears nor sends
            proc.stdin.flush()
            _frames(bus, 0.5)
            assert _answering_sync(bus) == set(range(1, 9)) - {3}
            proc.stdin.write("clear:9\nclear:2\n")  # its faults end: it answers again
            proc.stdin.flush()
            _frames(bus, 0.5)
            assert _answering_sync(bus) == set(range(1, 9))
        finally:
            bus.shutdown()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "fault on cable 9: the robot has cables 0..7" in err
    assert "fault 'nonsense': expected KIND:CABLE" in err
    assert err.count("fault on cable 9: the robot has cables 0..7") == 2  # drive:9, clear:9
