"""Recordings over a long run (daemon.process.recording_files and the recorders' series):
a new file at the size or age limit, each complete; the oldest files deleted beyond the
retention, never the current one nor another recording's; a pause below the free space
floor or on a full disk, resumed in a new file; other write errors stop the recorder;
the config's keys validated."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import can
import pytest
import yaml
from mcap.reader import make_reader

from cdpr import ConfigError
from daemon.config import load_config
from daemon.process.recording import CYCLE_TOPIC, CanRecorder, TelemetryRecorder
from daemon.process.recording_files import MB, RESUME_MIN, FileLimits, Series, file_limits
from tests.daemon.test_recording import cycle

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"


def old_file(directory: Path, name: str, size: int, age_s: float) -> Path:
    path = directory / name
    path.write_bytes(bytes(size))
    stamp = time.time() - age_s
    os.utime(path, (stamp, stamp))
    return path


def sequences(path: Path) -> list[int]:
    with path.open("rb") as stream:  # a complete file: summary and footer readable
        reader = make_reader(stream)
        assert reader.get_summary() is not None
        return [m.sequence for _, _, m in reader.iter_messages(topics=[CYCLE_TOPIC])]


# -- the series ----------------------------------------------------------------------------


def test_a_series_is_the_files_named_after_its_base_oldest_first(tmp_path: Path) -> None:
    newer = old_file(tmp_path, "cycle-20250102-030405.mcap", 10, 100)
    same_second = old_file(tmp_path, "cycle-20250102-030405-2.mcap", 10, 50)
    oldest = old_file(tmp_path, "cycle-20241231-235959.mcap", 10, 1000)
    for other in (
        "cycle.mcap",
        "cycle-notes.mcap",
        "cycle-20250102-030405.log",
        "x-20250102-030405.mcap",
    ):
        old_file(tmp_path, other, 10, 5000)
    (tmp_path / "cycle-20250101-000000.mcap").mkdir()  # not a file
    series = Series(tmp_path / "cycle.mcap", FileLimits())
    assert series.files() == [oldest, newer, same_second]
    assert series.next_path().name.startswith("cycle-") and series.next_path().suffix == ".mcap"


def test_rotation_is_due_at_either_limit() -> None:
    series = Series(Path("/x/cycle.mcap"), FileLimits(rotate_bytes=100, rotate_seconds=60.0))
    assert not series.rotation_due(99, 59.0)
    assert series.rotation_due(100, 0.0) and series.rotation_due(0, 60.0)
    assert not Series(Path("/x/c.mcap"), FileLimits()).rotation_due(10**12, 1e9)


def test_retention_deletes_the_oldest_first_and_never_the_current_file(tmp_path: Path) -> None:
    files = [old_file(tmp_path, f"bus-2025010{k}-000000.log", 3 * MB, 100 - k) for k in range(5)]
    unrelated = old_file(tmp_path, "bus-notes.log", 50 * MB, 1000)
    current = old_file(tmp_path, "bus-20250109-000000.log", 0, 0)
    limits = FileLimits(rotate_bytes=2 * MB, keep_bytes=8 * MB)  # 6 MB for the finished ones
    deleted = Series(tmp_path / "bus.log", limits).prune(current)
    assert deleted == files[:3]
    assert [p.exists() for p in files] == [False, False, False, True, True]
    assert current.exists() and unrelated.exists()


def test_retention_by_count_counts_the_current_file(tmp_path: Path) -> None:
    files = [old_file(tmp_path, f"bus-2025010{k}-000000.log", 10, 100 - k) for k in range(4)]
    current = old_file(tmp_path, "bus-20250109-000000.log", 0, 200)  # oldest mtime, still kept
    deleted = Series(tmp_path / "bus.log", FileLimits(keep_files=2)).prune(current)
    assert deleted == files[:3] and files[3].exists() and current.exists()


def test_a_paused_recording_resumes_with_a_margin_above_the_floor() -> None:
    assert FileLimits(min_free_bytes=0).resume_bytes == RESUME_MIN  # a full disk: no flapping
    assert FileLimits(min_free_bytes=1000 * MB).resume_bytes == 1100 * MB


# -- recorders writing a series --------------------------------------------------------------


def test_telemetry_begins_a_new_complete_file_at_the_size_limit(tmp_path: Path) -> None:
    limits = FileLimits(rotate_bytes=20_000, keep_files=10)
    recorder = TelemetryRecorder(
        tmp_path / "cycle.mcap", limits=limits, compression="none", chunk_size=4096
    )
    first = recorder.path
    assert first is not None and first.parent == tmp_path and first.name.startswith("cycle-")
    for k in range(200):
        recorder.record(cycle(k))
        if k % 20 == 19:
            recorder.flush()
            recorder.maintain()
    recorder.close()
    files = Series(tmp_path / "cycle.mcap", limits).files()
    assert recorder.files == len(files) >= 3 and files[0] == first
    assert all(f.stat().st_size < 2 * 20_000 for f in files)
    # every file complete, the sequence numbers running on from one to the next
    assert [s for f in files for s in sequences(f)] == list(range(200))
    assert recorder.status == "recording" and recorder.dropped == 0


def test_can_log_begins_a_new_file_at_the_age_limit(tmp_path: Path) -> None:
    limits = FileLimits(rotate_seconds=1e-6)
    recorder = CanRecorder(tmp_path / "bus.log", limits=limits, channel="can0", reorder=0.0)
    t0 = 1_700_000_000.0
    for k in range(3):
        message = can.Message(arbitration_id=0x181 + k, data=b"\x01", timestamp=t0 + k)
        recorder.record(message, rx=True)
        recorder.flush()
        recorder.maintain()  # older than a microsecond: the next file
    recorder.close()
    files = Series(tmp_path / "bus.log", limits).files()
    assert len(files) == 4 and recorder.files == 4  # the last one begun, and empty
    read = [[m.arbitration_id for m in can.LogReader(f)] for f in files]
    assert read == [[0x181], [0x182], [0x183], []]


def test_a_new_file_deletes_the_oldest_of_earlier_runs(tmp_path: Path) -> None:
    earlier = [old_file(tmp_path, f"cycle-2024010{k}-000000.mcap", 10, 1000 - k) for k in range(3)]
    recorder = TelemetryRecorder(tmp_path / "cycle.mcap", limits=FileLimits(keep_files=2))
    assert [p.exists() for p in earlier] == [False, False, True]
    assert recorder.path is not None and recorder.path.exists()
    recorder.close()


def test_below_the_floor_recording_pauses_and_resumes_in_a_new_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    free = [10 * MB]
    monkeypatch.setattr(Series, "free_bytes", lambda self: free[0])
    changes: list[tuple[str, str | None]] = []
    limits = FileLimits(min_free_bytes=5 * MB)
    recorder = TelemetryRecorder(tmp_path / "cycle.mcap", limits=limits)
    recorder.on_change = lambda r: changes.append((r.status, r.reason))
    first = recorder.path
    recorder.record(cycle(0))
    free[0] = 4 * MB
    recorder.maintain()
    assert recorder.status == "paused" and recorder.path is None
    assert recorder.reason.startswith(f"floor reached: 4.0 MB free on {tmp_path}, below ")
    assert "recording.min_free_mb (5)" in recorder.reason
    assert sequences(first) == [0]  # finished: complete and readable
    recorder.record(cycle(1))  # dropped, counted
    free[0] = 5 * MB + RESUME_MIN - 1
    recorder.maintain()
    assert recorder.status == "paused"  # not yet: a margin above the floor
    free[0] = 5 * MB + RESUME_MIN
    recorder.maintain()
    assert recorder.status == "recording" and recorder.reason is None
    assert recorder.path not in (None, first)
    recorder.record(cycle(2))
    second = recorder.path
    recorder.close()
    assert sequences(second) == [2] and recorder.dropped == 1
    assert [c[0] for c in changes] == ["paused", "recording"]


def test_a_recorder_below_the_floor_at_start_begins_paused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(Series, "free_bytes", lambda self: 0)
    recorder = CanRecorder(tmp_path / "bus.blf", limits=FileLimits(min_free_bytes=1))
    assert recorder.status == "paused" and recorder.path is None and recorder.files == 0
    assert list(tmp_path.iterdir()) == []
    recorder.close()


def test_a_full_disk_pauses_a_series_and_another_write_error_stops_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for code, status, reason in (
        (errno.ENOSPC, "paused", "disk full: OSError: No space left on device ("),
        (errno.EIO, "stopped", "write error: OSError: Input/output error ("),
    ):
        recorder = TelemetryRecorder(tmp_path / f"x{code}.mcap", limits=FileLimits())
        changes: list[str] = []
        recorder.on_change = lambda r, seen=changes: seen.append(r.status)

        def fail(code: int = code, **_: object) -> None:
            raise OSError(code, os.strerror(code))

        monkeypatch.setattr(recorder._writer, "add_message", fail)
        recorder.record(cycle(0))
        recorder.record(cycle(1))
        assert recorder.flush() == 0
        assert recorder.status == status and recorder.reason.startswith(reason), recorder.reason
        assert changes == [status] and recorder.dropped == 2 and recorder.path is None
        report = recorder.report()
        assert report["status"] == status and report["file"] is None
        recorder.close()


# -- the config ----------------------------------------------------------------------------


def test_the_defaults_bound_each_recording_for_a_long_run() -> None:
    limits = file_limits(load_config(CONFIG).recording)
    assert limits == FileLimits(
        rotate_bytes=256 * MB,
        rotate_seconds=3600.0,
        keep_bytes=4096 * MB,
        keep_files=None,
        min_free_bytes=1024 * MB,
    )


@pytest.mark.parametrize(
    ("section", "problem"),
    [
        ({"rotate_mb": 0}, "recording.rotate_mb: Input should be greater than 0 (got 0)"),
        ({"rotate_minutes": -1}, "recording.rotate_minutes: Input should be greater than 0"),
        ({"keep_files": 0}, "recording.keep_files: Input should be greater than or equal to 1"),
        ({"min_free_mb": -5}, "recording.min_free_mb: Input should be greater than or equal to 0"),
        ({"keep_mb": "lots"}, "recording.keep_mb: Input should be a valid number"),
        (
            {"rotate_mb": 500, "keep_mb": 100},
            "recording: keep_mb (100) is less than rotate_mb (500)",
        ),
        (
            {"rotate_mb": None, "rotate_minutes": None},
            "recording: keep_mb / keep_files need rotate_mb or rotate_minutes",
        ),
        ({"rotate_gb": 1}, "recording.rotate_gb: Extra inputs are not permitted"),
    ],
)
def test_bad_recording_keys_are_one_line_errors(
    tmp_path: Path, section: dict, problem: str
) -> None:
    data = yaml.safe_load(CONFIG.read_text())
    data["robot"] = str(ROOT / "config" / "robots" / "reference8.yaml")
    data["recording"] = section
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: {problem}"), caught.value
    assert "\n" not in str(caught.value)
