"""Telemetry (MCAP) and CAN (python-can log) recording: round trips, yielding, overflow."""

from __future__ import annotations

import asyncio
import datetime
import itertools
import json
import logging
import math

import can
import numpy as np
import pytest
from mcap.reader import make_reader

from daemon.process.recording import (
    CAN_LOG_SUFFIXES,
    CYCLE_SCHEMA,
    CYCLE_SCHEMA_NAME,
    CYCLE_TOPIC,
    CanRecorder,
    CycleRecord,
    TelemetryRecorder,
    encode_cycle,
)
from daemon.process.recording_files import session_path


def cycle(k: int, **changes) -> CycleRecord:
    fields = dict(
        t=0.002 * k,
        position=(0.1 * k, 0.0, 1.5),
        quaternion=(1.0, 0.0, 0.0, 0.0),
        twist=(0.01, 0.0, 0.0, 0.0, 0.0, 0.002),
        lengths=[1.0 + 0.001 * i for i in range(8)],
        tensions=[100.0 + i for i in range(8)],
        forces=[-100.0 - i for i in range(8)],
        safety="TRACKING",
        timing={"period": 0.002, "compute": 0.0004},
    )
    fields.update(changes)
    return CycleRecord(**fields)


def read_mcap(path):
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        messages = list(reader.iter_messages(topics=[CYCLE_TOPIC]))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return messages, metadata


def test_mcap_round_trip(tmp_path):
    path = tmp_path / "cycle.mcap"
    with TelemetryRecorder(path, metadata={"robot": "reference8"}) as recorder:
        recorder.record(cycle(0), log_time_ns=1_000)
        recorder.record(
            cycle(
                1,
                position=np.array([0.1, 0.2, 1.4]),  # numpy arrays are accepted
                tensions=np.arange(8.0),
                reference=((0.0, 0.0, 1.5), (0.7071067811865476, 0.0, 0.0, 0.7071067811865476)),
                faults=("drive 2 heartbeat lost",),
                safety="BRAKED",
                timing={"period": np.float64(0.0021), "overruns": 3},
            ),
            log_time_ns=2_000,
        )
        recorder.record(cycle(2, lengths=[math.nan] * 8, twist=[math.inf] * 6), log_time_ns=3_000)
    assert recorder.written == 3 and recorder.dropped == 0 and recorder.closed

    messages, metadata = read_mcap(path)
    assert len(messages) == 3
    schema, channel, message = messages[1]
    assert schema.name == CYCLE_SCHEMA_NAME and schema.encoding == "jsonschema"
    assert json.loads(schema.data) == CYCLE_SCHEMA
    assert channel.topic == CYCLE_TOPIC and channel.message_encoding == "json"
    assert channel.metadata == {"schema_version": "1"}
    assert [m.log_time for _, _, m in messages] == [1_000, 2_000, 3_000]
    assert [m.sequence for _, _, m in messages] == [0, 1, 2]
    decoded = json.loads(message.data)
    assert decoded["t"] == pytest.approx(0.002)
    assert decoded["pose"] == {
        "position": [0.1, 0.2, 1.4],
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
    }
    assert decoded["reference"]["quaternion"]["z"] == pytest.approx(math.sqrt(0.5))
    assert decoded["twist"] == {"linear": [0.01, 0.0, 0.0], "angular": [0.0, 0.0, 0.002]}
    assert decoded["tensions"] == list(range(8))
    assert decoded["forces"][7] == -107.0
    assert decoded["safety"] == {"state": "BRAKED", "faults": ["drive 2 heartbeat lost"]}
    assert decoded["timing"] == {"period": 0.0021, "overruns": 3}
    first = json.loads(messages[0][2].data)
    assert first["reference"] is None
    broken = json.loads(messages[2][2].data)  # strict JSON: non-finite numbers are null
    assert broken["lengths"] == [None] * 8
    assert broken["twist"] == {"linear": [None] * 3, "angular": [None] * 3}
    assert metadata["cdprd.session"] == {"robot": "reference8"}
    assert metadata["cdprd.recording"] == {"written": "3", "dropped": "0"}

    jsonschema = pytest.importorskip("jsonschema")
    for _, _, m in messages:
        jsonschema.validate(json.loads(m.data), CYCLE_SCHEMA)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_mcap_compressions(tmp_path, compression):
    path = tmp_path / f"{compression}.mcap"
    with TelemetryRecorder(path, compression=compression, chunk_size=4096) as recorder:
        for k in range(50):
            recorder.record(cycle(k))
    messages, _ = read_mcap(path)
    assert [json.loads(m.data)["t"] for _, _, m in messages] == [0.002 * k for k in range(50)]


def test_bad_arguments_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="compression 'gzip' is unknown"):
        TelemetryRecorder(tmp_path / "x.mcap", compression="gzip")
    with pytest.raises(ValueError, match="capacity must be at least 1"):
        TelemetryRecorder(tmp_path / "x.mcap", capacity=0)
    with pytest.raises(ValueError, match="budget must be a non-negative time"):
        CanRecorder(tmp_path / "x.log", budget=-1.0)
    with pytest.raises(ValueError, match="twist must have 6"):
        encode_cycle(cycle(0, twist=(0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="3 position and 4 quaternion"):
        encode_cycle(cycle(0, quaternion=(1.0, 0.0, 0.0)))
    with pytest.raises(FileNotFoundError):
        TelemetryRecorder(tmp_path / "missing-dir" / "x.mcap")


def test_recordings_are_never_overwritten(tmp_path):
    for name, make in (("old.mcap", TelemetryRecorder), ("old.log", CanRecorder)):
        (tmp_path / name).write_bytes(b"evidence")
        with pytest.raises(FileExistsError, match="exists; recordings are never overwritten"):
            make(tmp_path / name)
        assert (tmp_path / name).read_bytes() == b"evidence"


def test_session_path_names_each_run(tmp_path):
    start = datetime.datetime(2025, 1, 2, 3, 4, 5)
    first = session_path(tmp_path / "cycle.mcap", start)
    assert first == tmp_path / "cycle-20250102-030405.mcap"
    first.touch()
    assert session_path(tmp_path / "cycle.mcap", start) == tmp_path / "cycle-20250102-030405-2.mcap"
    assert session_path(tmp_path / "bus.blf").suffix == ".blf"


def test_overflow_is_counted_when_the_writer_is_stalled(tmp_path):
    path = tmp_path / "stalled.mcap"
    recorder = TelemetryRecorder(path, capacity=10)
    for k in range(25):  # nobody writes: the queue fills, then records are dropped
        recorder.record(cycle(k))
    assert recorder.pending == 10 and recorder.dropped == 15
    assert recorder.flush(budget=0.0) == 1  # a spent budget still writes one record
    assert recorder.flush(budget=60.0) == 9 and recorder.pending == 0
    recorder.record(cycle(25))  # room again
    recorder.close()
    recorder.record(cycle(26))  # after close: counted, not raised
    assert recorder.written == 11 and recorder.dropped == 16
    messages, metadata = read_mcap(path)
    # sequence numbers count every record() call, so the gap shows the loss
    assert [m.sequence for _, _, m in messages] == [*range(10), 25]
    assert metadata["cdprd.recording"] == {"written": "11", "dropped": "15"}


def test_run_task_yields_to_the_loop_when_its_budget_is_spent(tmp_path):
    path = tmp_path / "task.mcap"
    recorder = TelemetryRecorder(path, budget=0.0)  # one record per loop pass
    seen: list[int] = []

    async def main() -> None:
        for k in range(100):
            recorder.record(cycle(k))
        writer = asyncio.create_task(recorder.run(period=0.001))

        async def observer() -> None:  # stands in for the control cycle
            while recorder.pending:
                seen.append(recorder.pending)
                await asyncio.sleep(0)

        await asyncio.wait_for(observer(), 10)
        for k in range(100, 130):  # recording continues while the task runs
            recorder.record(cycle(k))
            await asyncio.sleep(0.0005)
        while recorder.pending:
            await asyncio.wait_for(asyncio.sleep(0.01), 10)
        writer.cancel()
        await asyncio.gather(writer, return_exceptions=True)

    asyncio.run(main())
    recorder.close()
    assert recorder.written == 130 and recorder.dropped == 0
    written_between_looks = [a - b for a, b in itertools.pairwise(seen) if a != b]
    assert written_between_looks == [1] * 99  # the observer ran after every record
    messages, _ = read_mcap(path)
    assert [m.sequence for _, _, m in messages] == list(range(130))


def test_write_failure_stops_recording_without_raising(tmp_path, caplog, monkeypatch):
    recorder = TelemetryRecorder(tmp_path / "full.mcap")

    def disk_full(**_: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(recorder._writer, "add_message", disk_full)
    for k in range(5):
        recorder.record(cycle(k))
    with caplog.at_level(logging.ERROR, logger="daemon.process.recording"):
        assert recorder.flush() == 0
        asyncio.run(asyncio.wait_for(recorder.run(period=0.001), 5))  # returns: failed
    assert recorder.status == "stopped"  # a single file cannot go on in another
    assert recorder.reason.startswith("disk full: OSError: No space left on device")
    assert caplog.text.count("stopped") == 1
    recorder.record(cycle(5))
    assert recorder.pending == 0 and recorder.dropped == 6
    recorder.close()


# -- CAN --------------------------------------------------------------------------------


def frames() -> list[tuple[can.Message, bool]]:
    """(frame, rx): feedback received, commands sent (built without channel/timestamp)."""
    t0 = 1_700_000_000.0
    rx = dict(channel="can0")
    return [
        (can.Message(timestamp=t0, arbitration_id=0x181, data=bytes(range(8)), **rx), True),
        (can.Message(arbitration_id=0x201, data=b"\x0f\x00\x10\x27"), False),
        (can.Message(timestamp=t0 + 0.0005, arbitration_id=0x80, data=b"", **rx), True),
        (can.Message(arbitration_id=0x1F000A7, is_extended_id=True, data=b"\xaa\x55"), False),
        (can.Message(timestamp=t0 + 0.0021, arbitration_id=0x701, data=b"\x05", **rx), True),
    ]


@pytest.mark.parametrize("suffix", CAN_LOG_SUFFIXES)
def test_can_log_round_trip(tmp_path, suffix):
    path = tmp_path / f"bus{suffix}"
    sent = frames()
    stamps = [1_700_000_000.0003, 1_700_000_000.0012]  # send times of the tx frames
    with CanRecorder(path, channel="can0") as recorder:
        for message, rx in sent:
            recorder.record(message, rx=rx, timestamp=None if rx else stamps.pop(0))
            assert message.is_rx is True  # the caller's frame is not modified
    assert recorder.written == len(sent)

    read = list(can.LogReader(path))
    assert len(read) == len(sent)
    t0 = 1_700_000_000.0
    expected_times = [t0, t0 + 0.0003, t0 + 0.0005, t0 + 0.0012, t0 + 0.0021]
    for (message, rx), back in zip(sent, read, strict=True):
        assert back.arbitration_id == message.arbitration_id
        assert back.is_extended_id == message.is_extended_id
        assert bytes(back.data) == bytes(message.data) and back.dlc == message.dlc
        if suffix != ".csv":  # CSV keeps neither direction nor channel
            assert back.is_rx == rx
    # relative times survive in every format (ASC and TRC store them relative to the start)
    t_back = [m.timestamp - read[0].timestamp for m in read]
    t_sent = [t - expected_times[0] for t in expected_times]
    assert t_back == pytest.approx(t_sent, abs=2e-6)


def test_can_recorder_rejects_unknown_suffix(tmp_path):
    with pytest.raises(ValueError, match=r"suffix '.pcap' is not one of .asc, .blf"):
        CanRecorder(tmp_path / "bus.pcap")
    with pytest.raises(ValueError, match=r"suffix '\(none\)'"):
        CanRecorder(tmp_path / "bus")


def test_can_overflow_and_default_timestamps(tmp_path):
    path = tmp_path / "bus.log"
    recorder = CanRecorder(path, channel="can0", capacity=4)
    for k in range(10):
        recorder.record(can.Message(arbitration_id=0x200 + k, data=b"\x01"), rx=False)
    assert recorder.pending == 4 and recorder.dropped == 6
    recorder.close()
    read = list(can.LogReader(path))
    assert [m.arbitration_id for m in read] == [0x200, 0x201, 0x202, 0x203]
    assert all(not m.is_rx and m.channel == "can0" and m.timestamp > 1e9 for m in read)


def test_mcap_records_foxglove_standard_channels_beside_the_cycles(tmp_path):
    from mcap_protobuf.decoder import DecoderFactory

    from cdpr import Robot
    from daemon.process.scene import SCENE_TOPIC, TF_TOPIC, SceneBuilder, standard_channels
    from tests.conftest import ROBOTS

    robot = Robot.from_yaml(ROBOTS / "reference8.yaml")
    builder = SceneBuilder(robot, ((-1, -1, 0), (1, 1, 2)))
    path = tmp_path / "cycle.mcap"
    with TelemetryRecorder(path, channels=standard_channels()) as recorder:
        for k in range(3):
            record = cycle(k, reference=((0.0, 0.0, 1.5), (1.0, 0.0, 0.0, 0.0)))
            recorder.record(record, log_time_ns=1_000 + k)
            recorder.log_messages(builder.encode(record, 1_000 + k), 1_000 + k)
        brake = builder.encode_event({"event": "brake", "trigger": "x"}, 2_000)
        recorder.log_messages(brake, 2_000)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        schemas = {c.topic: (s.name, s.encoding, c.message_encoding)
                   for s, c, _m in reader.iter_messages()}
        decoded = {}
        sequences = {}
        for _s, channel, message, proto in reader.iter_decoded_messages(
            topics=[TF_TOPIC, SCENE_TOPIC]
        ):
            decoded.setdefault(channel.topic, []).append(proto)
            sequences.setdefault(channel.topic, []).append(message.sequence)
    assert schemas == {
        CYCLE_TOPIC: (CYCLE_SCHEMA_NAME, "jsonschema", "json"),
        "/tf": ("foxglove.FrameTransforms", "protobuf", "protobuf"),
        "/cdpr/scene": ("foxglove.SceneUpdate", "protobuf", "protobuf"),
        "/cdpr/pose": ("foxglove.PoseInFrame", "protobuf", "protobuf"),
        "/cdpr/reference_pose": ("foxglove.PoseInFrame", "protobuf", "protobuf"),
        "/cdpr/series": ("cdprd.Series", "jsonschema", "json"),
        "/cdpr/log": ("foxglove.Log", "protobuf", "protobuf"),
    }
    platforms = [m.transforms[0].translation.x for m in decoded[TF_TOPIC]]
    assert platforms == pytest.approx([0.0, 0.1, 0.2])
    assert [len(m.entities) for m in decoded[SCENE_TOPIC]] == [5, 5, 5]
    assert sequences[TF_TOPIC] == [0, 1, 2]  # counted per channel
