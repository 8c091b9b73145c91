"""`cdprd run --sim` as its own process with the `recording:` section on: a flight over
zenoh leaves an MCAP cycle telemetry file and a python-can CAN log that the stock readers
open, with the content the flight must have produced; a recording file that cannot be
created stops the start-up with one line naming the key and the file."""

from __future__ import annotations

import itertools
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest
import yaml
from mcap.reader import make_reader

from daemon.interface.client import CdprClient
from daemon.process.recording import CYCLE_SCHEMA, CYCLE_SCHEMA_NAME, CYCLE_TOPIC, CanRecorder
from tests.loopback import free_port
from tests.processes import connect, finish, stop_impatiently, wait_status

pytestmark = pytest.mark.slow  # the daemon as processes: the slow suites (CI runs them)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
PREFIX = "cdpr/reference8"
SYNC_ID, TPDO1_BASE, RPDO1_BASE = 0x080, 0x180, 0x200  # drivers/cia402/codec.py
TARGET = (0.08, 0.0, 1.3)  # m; the trajectory's last waypoint (home is (0, 0, 1.25))


def _write_config(tmp_path: Path, port: int, recording: dict[str, str]) -> tuple[Path, dict]:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    data["recording"] = recording
    path = tmp_path / "cdprd.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, data


def _start(config: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "daemon.cli", "run", "--config", str(config), "--sim"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _finish(proc: subprocess.Popen, impatient: bool = True) -> str:
    """SIGTERM every 20 ms until the daemon exits (or with `impatient` false just wait),
    and its output."""
    if impatient:
        stop_impatiently(proc)
    return finish(proc, terminate=False)


def _wait_state(client: CdprClient, state: str, timeout: float) -> None:
    end = time.monotonic() + timeout
    while (now := client.status()["state"]) != state:
        assert time.monotonic() < end, f"still {now}, never {state}"
        time.sleep(0.05)


def _only(directory: Path, pattern: str) -> Path:
    files = sorted(directory.glob(pattern))
    assert len(files) == 1, f"expected one {pattern} in {directory}: {files}"
    return files[0]


def _finite(value: object) -> bool:
    """True if every number in a decoded JSON value is finite (null means non-finite)."""
    if value is None:
        return False
    if isinstance(value, float | int):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    return True


@pytest.mark.timeout(60)
def test_a_flight_is_recorded_to_mcap_and_a_can_log(tmp_path: Path) -> None:
    port = free_port()
    recordings = tmp_path / "rec"
    recordings.mkdir()
    config, data = _write_config(
        tmp_path, port, {"telemetry": "rec/cycle.mcap", "can_log": "rec/bus.log"}
    )
    rate = data["controller"]["rate_hz"]
    nodes = data["drives"]["nodes"]
    proc = _start(config)
    try:
        with connect(port, proc) as client:
            wait_status(client, "idle", 10.0)  # zenoh answers while the drives start
            asked = time.monotonic()
            client.enable()
            enabled = time.monotonic()
            quat = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}
            client.send_trajectory(
                {
                    "waypoints": [
                        {"t": 0.0, "position": [0.0, 0.0, 1.25], "quaternion": quat},
                        {"t": 1.0, "position": list(TARGET), "quaternion": quat},
                    ]
                }
            )
            _wait_state(client, "tracking", 5.0)
            _wait_state(client, "hold", 10.0)
            time.sleep(0.3)  # a little hold after the flight
            stopping = time.monotonic()
    finally:
        out = _finish(proc)  # the recordings are complete even with SIGTERMs during clean-up
    stopped = time.monotonic()
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
    assert "incomplete" not in out, out  # nothing dropped in the core or the companion

    # -- MCAP cycle telemetry ------------------------------------------------------------
    with _only(recordings, "cycle-*.mcap").open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        # the cycle records beside the scene's standard channels (tests/daemon/test_live_view.py)
        (channel,) = [c for c in summary.channels.values() if c.topic == CYCLE_TOPIC]
        schema = summary.schemas[channel.schema_id]
        assert channel.message_encoding == "json"
        assert (schema.name, schema.encoding) == (CYCLE_SCHEMA_NAME, "jsonschema")
        assert json.loads(schema.data) == CYCLE_SCHEMA
        messages = [m for _, _, m in reader.iter_messages([CYCLE_TOPIC], log_time_order=False)]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    records = [json.loads(m.data) for m in messages]
    n = len(records)
    written = str(summary.statistics.message_count)
    assert metadata["cdprd.recording"] == {"written": written, "dropped": "0"}
    assert [m.sequence for m in messages] == list(range(n))  # nothing lost
    log_times = [m.log_time for m in messages]
    assert all(a <= b for a, b in itertools.pairwise(log_times))
    t = [r["t"] for r in records]
    assert all(a < b for a, b in itertools.pairwise(t))
    span = t[-1] - t[0]
    # one record per control cycle while enabled: at most one per period, and (loosely)
    # most of them; the records span about the time the robot was enabled
    assert 0.5 * rate * span <= n <= rate * span + 3
    assert 0.5 * (stopping - enabled) <= span <= stopped - asked
    for record in records:
        assert _finite({k: v for k, v in record.items() if k != "safety"}), record
        assert len(record["lengths"]) == len(record["tensions"]) == len(nodes)
        assert min(record["tensions"]) > 0.0  # every cable taut
    states = [r["safety"]["state"] for r in records]
    assert set(states) <= {"hold", "tracking"} and states[0] == "hold"
    tracking = [r for r in records if r["safety"]["state"] == "tracking"]
    assert len(tracking) >= 0.5 * rate * 1.0  # the 1 s flight, recorded while tracking
    x_ref = [r["reference"]["position"][0] for r in tracking]
    assert x_ref[0] < 0.01 and x_ref[-1] == pytest.approx(TARGET[0], abs=1e-3)
    assert all(a <= b + 1e-9 for a, b in itertools.pairwise(x_ref))
    assert records[-1]["pose"]["position"] == pytest.approx(list(TARGET), abs=3e-3)

    # -- raw CAN log ---------------------------------------------------------------------
    frames = list(can.LogReader(_only(recordings, "bus-*.log")))
    stamps = [f.timestamp for f in frames]
    assert all(a <= b for a, b in itertools.pairwise(stamps)), "not in time order"
    assert len({f.channel for f in frames}) == 1  # sent and received on the one bus
    by_id: dict[int, list[can.Message]] = {}
    for frame in frames:
        by_id.setdefault(frame.arbitration_id, []).append(frame)
    syncs = by_id[SYNC_ID]
    assert all(not f.is_rx and f.dlc == 0 for f in syncs)
    for node in nodes:
        feedback, commands = by_id[TPDO1_BASE + node], by_id[RPDO1_BASE + node]
        assert all(f.is_rx for f in feedback) and not any(f.is_rx for f in commands)
        assert len(feedback) >= 0.8 * len(syncs)  # each drive answers (nearly) every SYNC
        assert abs(len(commands) - n) <= 3  # one command per recorded control cycle
    # NMT, SYNC, the host's heartbeat (node 127, the drives consume it), and the
    # configured drives' PDOs, SDOs and heartbeats: nothing else
    host = 0x700 + 127
    assert by_id[host] and all(not f.is_rx for f in by_id[host])
    node_of = {ident: ident & 0x7F for ident in by_id if ident not in (0x000, SYNC_ID, host)}
    assert set(node_of.values()) == set(nodes)
    assert {ident & ~0x7F for ident in node_of} <= {0x180, 0x200, 0x280, 0x300, 0x580, 0x600, 0x700}

    jsonschema = pytest.importorskip("jsonschema")
    for record in records[:: max(1, n // 50)]:
        jsonschema.validate(record, CYCLE_SCHEMA)


@pytest.mark.parametrize(
    ("recording", "key", "where", "reason"),
    [
        ({"telemetry": "missing/cycle.mcap"}, "recording.telemetry", "missing", "No such file"),
        (
            {"telemetry": "cycle.mcap", "can_log": "a-file/bus.log"},
            "recording.can_log",
            "a-file",
            "Not a directory",
        ),
        ({"can_log": "read-only/bus.blf"}, "recording.can_log", "read-only", "Permission denied"),
    ],
    ids=["missing-directory", "not-a-directory", "read-only-directory"],
)
@pytest.mark.timeout(60)
def test_an_unwritable_recording_stops_start_up_with_a_clear_error(
    tmp_path: Path, recording: dict[str, str], key: str, where: str, reason: str
) -> None:
    (tmp_path / "a-file").write_text("not a directory")
    read_only = tmp_path / "read-only"
    read_only.mkdir(mode=0o555)
    if where == "read-only" and os.access(read_only, os.W_OK):
        pytest.skip("running as root: a read-only directory is writable")
    config, _ = _write_config(tmp_path, free_port(), recording)
    proc = _start(config)
    out = _finish(proc, impatient=False)  # it must exit by itself
    assert proc.returncode > 0, out  # exited with an error, not killed
    assert "Traceback" not in out, out
    (line,) = [x for x in out.splitlines() if x.startswith("error:")]
    assert key in line and f"{tmp_path / where}/" in line and reason in line, out
    if recording.get("telemetry") == "cycle.mcap":  # opened before the failing one:
        with _only(tmp_path, "cycle-*.mcap").open("rb") as stream:  # closed, valid, empty
            assert list(make_reader(stream).iter_messages()) == []


def test_can_log_frames_are_written_in_time_order(tmp_path: Path) -> None:
    """A received frame reaches the recorder when the loop drains the bus, possibly after
    a frame sent later; the log is nevertheless in time order (unit level)."""
    path = tmp_path / "bus.log"
    t0 = 1_700_000_000.0
    sent_late = [(0x080, t0 + 0.0010, False), (0x181, t0 + 0.0004, True)]
    sent_late += [(0x201, t0 + 0.0012, False), (0x182, t0 + 0.0011, True)]
    with CanRecorder(path, channel="can0", reorder=0.01) as recorder:
        for ident, stamp, rx in sent_late:
            message = can.Message(arbitration_id=ident, data=b"\x00", timestamp=stamp)
            recorder.record(message, rx=rx, timestamp=stamp)
    read = list(can.LogReader(path))
    assert [m.arbitration_id for m in read] == [0x181, 0x080, 0x182, 0x201]
    assert [m.is_rx for m in read] == [True, False, True, False]
    with pytest.raises(ValueError, match="reorder must be a time >= 0 s"):
        CanRecorder(tmp_path / "x.log", reorder=-1.0)
