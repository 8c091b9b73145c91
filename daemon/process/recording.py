"""Optional recording of cycle telemetry (MCAP) and raw CAN traffic (python-can log files).

The control cycle must never wait for a disk.  Both recorders share one discipline: the
cycle's `record()` only appends to a bounded in-memory queue (O(1), no I/O, no encoding);
when the queue is full the record is dropped and counted.  A task on the same event loop
(`run()`) writes the queue out every `period` seconds and yields to the loop whenever a
pass has used its time `budget` (at least one record per pass; an MCAP record takes
≈ 20 µs, a CAN frame 1–5 µs).  A pass that fills an MCAP chunk or a BLF container also
compresses it, ≈ 0.3–1.5 ms at the default sizes; otherwise a cycle waits at most about
one budget.  Writing happens on the loop rather than in a thread on purpose: a CPU-bound
writer thread holds the GIL for up to the interpreter's switch interval (5 ms) before the
loop thread gets it back, longer than a 1 kHz cycle.

Given FileLimits (the config's `recording:` limits, daemon.process.recording_files), a
recorder writes a series of files: a new one at the rotation limits, the oldest deleted
beyond the retention limits, none while free space is below the floor.  Its `status`
says whether it records, is paused (below the floor, or the disk full: it resumes in a
new file once there is room again) or stopped (another write error: for good), and
`reason` why; `on_change` hears every change, so that the daemon can say so in its
status, its state and an event.  Nothing of this ever reaches the cycle.

Values are read when written, not when recorded: hand `record()` objects the cycle does
not modify afterwards (tuples, lists from `.tolist()`, or freshly allocated arrays).

A recorder never overwrites a file (the recording of the run before a watchdog restart is
the evidence of why it stalled): each file is named after the time it began
(recording_files.session_path).
"""

from __future__ import annotations

import asyncio
import copy
import errno
import heapq
import itertools
import json
import logging
import math
import os
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Generic, Literal, Self, TypeVar

import can
from mcap.writer import CompressionType, Writer

from daemon.process.recording_files import MB, FileLimits, Series

log = logging.getLogger(__name__)

Item = TypeVar("Item")
Status = Literal["recording", "paused", "stopped"]
CHECK_PERIOD = 1.0  # s between looks at free space and the current file's size and age
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


def _refuse_existing(path: Path, what: str) -> None:
    if path.exists():
        raise FileExistsError(f"{what} {path} exists; recordings are never overwritten")


class _Spool(ABC, Generic[Item]):
    """A bounded queue filled by the cycle and written out by `flush`/`run` to `path`, or
    with `limits` to a series of files named after `path` (see the module doc).
    Subclasses validate their options, then call `_begin`."""

    def __init__(
        self, kind: str, path: Path, capacity: int, budget: float, limits: FileLimits | None
    ) -> None:
        if capacity < 1:
            raise ValueError(f"{kind} {path}: capacity must be at least 1, not {capacity}")
        if not budget >= 0:
            raise ValueError(f"{kind} {path}: budget must be a non-negative time (s), not {budget}")
        self.kind = kind  # "telemetry recording", "CAN recording"
        self.capacity = capacity
        self.budget = budget
        self.series = None if limits is None else Series(path, limits)
        self.path: Path | None = None  # the file being written
        self.files = 0  # files begun
        self._opened_at = 0.0
        self._checked_at = -math.inf
        self._queue: deque[Item] = deque()
        self.dropped = 0  # records lost: queue full, or recorder paused, stopped or closed
        self.written = 0
        self.status: Status = "recording"
        self.reason: str | None = None  # why it is paused or stopped
        self.on_change: Callable[[Self], None] | None = None  # hears every status change
        self.closed = False

    def _begin(self, path: Path) -> None:
        """The first file: `path` itself, or with limits the series' first, or none yet
        while free space is below the floor.  A file that cannot be created raises."""
        if self.series is None:
            self._start(path)
            return
        first = self.series.next_path()
        try:
            free = self.series.free_bytes()
        except OSError:  # no such directory, say: creating the file says so, naming it
            free = None
        if free is not None and free < self.series.limits.min_free_bytes:
            self._set("paused", self._below_floor(free))
        else:
            self._start(first)
            self._prune()

    @property
    def pending(self) -> int:
        """Records queued and not yet written."""
        return len(self._queue)

    def report(self) -> dict[str, Any]:
        """What the daemon's status and state say of this recorder."""
        return {
            "status": self.status,
            "reason": self.reason,
            "file": None if self.path is None else str(self.path),
            "files": self.files,
            "written": self.written,
            "dropped": self.dropped,
        }

    def _push(self, item: Item) -> None:
        if self.closed or self.status != "recording" or len(self._queue) >= self.capacity:
            self.dropped += 1
        else:
            self._queue.append(item)

    def flush(self, budget: float | None = None) -> int:
        """Write queued records now: all of them, or (with `budget`) until `budget`
        seconds have passed, at least one.  Returns how many were written."""
        count = 0
        queue = self._queue
        deadline = None if budget is None else time.perf_counter() + budget
        try:
            while queue:
                self._write(queue[0])
                queue.popleft()
                count += 1
                if deadline is not None and time.perf_counter() >= deadline:
                    break
            if count:
                self._sync()
        except Exception as exc:  # a recorder must never take the daemon down
            self._write_failed(exc)
        self.written += count
        return count

    async def run(self, period: float = 0.05) -> None:
        """Write the queue out every `period` seconds, yielding to the loop after each
        `budget` of writing, and look after the files (`maintain`) every CHECK_PERIOD,
        until the recorder is closed or stopped.  Cancel the task, then `close()`."""
        if not period > 0:
            raise ValueError(f"{self.kind}: period must be positive, not {period}")
        while not self.closed and self.status != "stopped":
            await asyncio.sleep(period)
            if time.monotonic() - self._checked_at >= CHECK_PERIOD:
                self.maintain()
            while self._queue and self.status == "recording" and not self.closed:
                self.flush(self.budget)
                await asyncio.sleep(0)

    def maintain(self) -> None:
        """With limits: pause below the free space floor, resume in a new file once
        there is room again, begin a new file when the current one is complete."""
        now = self._checked_at = time.monotonic()
        series = self.series
        if series is None or self.closed or self.status == "stopped":
            return
        try:
            free = series.free_bytes()
        except OSError as exc:  # the directory is gone, say
            self._write_failed(exc)
            return
        limits = series.limits
        if self.status == "recording" and free < limits.min_free_bytes:
            self.flush()
            self._end_file()
            if self.status == "recording":
                self._set("paused", self._below_floor(free))
        elif self.status == "paused" and free >= limits.resume_bytes:
            self._next_file(f"{free / MB:.0f} MB free")
        elif self.status == "recording" and self.path is not None:
            try:
                size = os.stat(self.path).st_size
            except OSError as exc:
                self._write_failed(exc)
                return
            if series.rotation_due(size, now - self._opened_at):
                self.flush()
                self._end_file()
                if self.status == "recording":
                    self._next_file()

    def close(self) -> None:
        """Write what is queued, finish the file and stop accepting records."""
        if self.closed:
            return
        if self.status == "recording":
            self.flush()
        self.closed = True
        self._end_file()
        if self.dropped:
            log.warning("%s incomplete: %d records dropped", self.kind, self.dropped)

    def _start(self, path: Path) -> None:
        self._open(path)
        self.path = path
        self.files += 1
        self._opened_at = time.monotonic()

    def _next_file(self, resumed: str = "") -> None:
        """Begin the series' next file and delete the oldest beyond the retention; the
        status says so if it cannot be created."""
        assert self.series is not None
        path = self.series.next_path()
        try:
            self._start(path)
        except Exception as exc:
            self._write_failed(exc)
            return
        self._prune()
        if resumed:
            self._set("recording", None, f"resumed in {path} ({resumed})")

    def _prune(self) -> None:
        """The series' oldest files beyond its retention deleted, never the current one."""
        assert self.series is not None
        for old in self.series.prune(self.path):
            log.info("%s: deleted %s (recording.keep_mb / keep_files)", self.kind, old)

    def _end_file(self) -> None:
        """Complete and close the current file, if any."""
        if self.path is None:
            return
        try:
            self._finish()
        except Exception as exc:
            self._write_failed(exc)
        self.path = None

    def _write_failed(self, exc: Exception) -> None:
        """Drop what is queued and the file; a full disk pauses a series, anything else
        stops the recorder."""
        self.dropped += len(self._queue)
        self._queue.clear()
        full = isinstance(exc, OSError) and exc.errno in DISK_FULL
        what = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        where = f" ({self.path})" if self.path is not None else ""
        reason = f"{'disk full' if full else 'write error'}: {type(exc).__name__}: {what}{where}"
        if self.path is not None:
            self.path = None
            try:
                self._abandon()
            except Exception as again:  # the file is lost either way
                log.debug("%s: closing after %s: %s", self.kind, reason, again)
        if self.status == "stopped":
            return
        paused = full and self.series is not None and not self.closed
        self._set("paused" if paused else "stopped", reason)

    def _below_floor(self, free: int) -> str:
        assert self.series is not None
        floor = self.series.limits.min_free_bytes / MB
        return (
            f"floor reached: {free / MB:.1f} MB free on {self.series.base.parent}, below "
            f"recording.min_free_mb ({floor:g})"
        )

    def _set(self, status: Status, reason: str | None, said: str = "") -> None:
        self.status, self.reason = status, reason
        if status == "recording":
            log.info("%s %s", self.kind, said)
        elif status == "paused":
            log.error("%s paused until there is room again: %s", self.kind, reason)
        else:
            log.error("%s stopped: %s", self.kind, reason)
        if self.on_change is not None:
            self.on_change(self)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def _open(self, path: Path) -> None:
        """Create the file `path` (never an existing one) and begin it."""

    @abstractmethod
    def _write(self, item: Item) -> None:
        """Encode and write one record."""

    @abstractmethod
    def _sync(self) -> None:
        """Push written records towards the disk after a pass."""

    @abstractmethod
    def _finish(self) -> None:
        """Complete and close the current file."""

    @abstractmethod
    def _abandon(self) -> None:
        """Close the current file after a write error, completing nothing."""


# -- cycle telemetry (MCAP) ----------------------------------------------------------------

CYCLE_TOPIC = "/cdpr/cycle"
CYCLE_SCHEMA_NAME = "cdprd.Cycle"
CYCLE_SCHEMA_VERSION = 1

_NUMBER = {"type": ["number", "null"]}  # null: a value that was NaN or infinite
_VECTOR3 = {"type": "array", "items": _NUMBER, "minItems": 3, "maxItems": 3}
_PER_CABLE = {"type": "array", "items": _NUMBER}
_POSE = {
    "type": "object",
    "properties": {
        "position": {**_VECTOR3, "description": "platform reference point p, world frame (m)"},
        "quaternion": {
            "type": "object",
            "description": "orientation R platform->world",
            "properties": {k: _NUMBER for k in "wxyz"},
            "required": list("wxyz"),
            "additionalProperties": False,
        },
    },
    "required": ["position", "quaternion"],
    "additionalProperties": False,
}

CYCLE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": CYCLE_SCHEMA_NAME,
    "description": (
        "One control cycle of cdprd (SI units; DESIGN §3 conventions). Non-finite numbers "
        f"are recorded as null. Schema version {CYCLE_SCHEMA_VERSION}."
    ),
    "type": "object",
    "properties": {
        "t": {**_NUMBER, "description": "cycle time on the daemon's monotonic clock (s)"},
        "pose": {**_POSE, "description": "measured pose (forward kinematics)"},
        "reference": {
            "anyOf": [_POSE, {"type": "null"}],
            "description": "requested pose, null when none is active",
        },
        "twist": {
            "type": "object",
            "description": "mixed twist: linear = dp/dt (m/s), angular = world-frame ω (rad/s)",
            "properties": {"linear": _VECTOR3, "angular": _VECTOR3},
            "required": ["linear", "angular"],
            "additionalProperties": False,
        },
        "lengths": {**_PER_CABLE, "description": "measured cable lengths (m), cable order"},
        "tensions": {**_PER_CABLE, "description": "cable tensions t = f0 - f (N)"},
        "forces": {**_PER_CABLE, "description": "commanded actuator forces along +l (N)"},
        "safety": {
            "type": "object",
            "properties": {
                "state": {"type": "string"},
                "faults": {"type": "array", "items": {"type": "string"}},
            },
            "required": ["state", "faults"],
            "additionalProperties": False,
        },
        "timing": {
            "type": "object",
            "description": "cycle timing figures (s unless the name says otherwise)",
            "additionalProperties": _NUMBER,
        },
    },
    "required": ["t", "pose", "twist", "lengths", "tensions", "forces", "safety", "timing"],
    "additionalProperties": False,
}


@dataclass(frozen=True, slots=True)
class CycleRecord:
    """What one control cycle records.  Sequences may be tuples, lists or numpy arrays
    (not modified after recording); `quaternion` is (w, x, y, z); `twist` is (v, ω);
    `reference` is (position, quaternion) or None."""

    t: float
    position: Sequence[float]
    quaternion: Sequence[float]
    twist: Sequence[float]
    lengths: Sequence[float]
    tensions: Sequence[float]
    forces: Sequence[float]
    safety: str
    faults: Sequence[str] = ()
    timing: Mapping[str, float] = field(default_factory=dict)
    reference: tuple[Sequence[float], Sequence[float]] | None = None

    def to_json(self) -> dict[str, Any]:
        """The record as the JSON object described by CYCLE_SCHEMA."""
        twist = _plain(self.twist)
        if len(twist) != 6:
            raise ValueError(f"twist must have 6 components (v, ω), not {len(twist)}")
        return {
            "t": self.t,
            "pose": _pose_json(self.position, self.quaternion),
            "reference": None if self.reference is None else _pose_json(*self.reference),
            "twist": {"linear": twist[:3], "angular": twist[3:]},
            "lengths": _plain(self.lengths),
            "tensions": _plain(self.tensions),
            "forces": _plain(self.forces),
            "safety": {"state": self.safety, "faults": list(self.faults)},
            "timing": dict(self.timing),
        }


def _plain(values: Any) -> list:
    """A list of Python numbers from a sequence or numpy array."""
    return values.tolist() if hasattr(values, "tolist") else list(values)


def _pose_json(position: Sequence[float], quaternion: Sequence[float]) -> dict[str, Any]:
    p, q = _plain(position), _plain(quaternion)
    if len(p) != 3 or len(q) != 4:
        raise ValueError(f"a pose needs 3 position and 4 quaternion values, got {len(p)}/{len(q)}")
    return {"position": p, "quaternion": dict(zip("wxyz", q, strict=True))}


def _finite(value: Any) -> Any:
    """`value` with every NaN or infinity replaced by None (strict JSON has neither)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if hasattr(value, "item"):  # a numpy scalar
        return _finite(value.item())
    return value


def _scalar(value: Any) -> Any:
    if hasattr(value, "item"):  # numpy scalars, e.g. a timing figure from np.median
        return value.item()
    raise TypeError(f"cannot record a {type(value).__name__} as JSON")


def encode_cycle(record: CycleRecord) -> bytes:
    """The JSON bytes of one record; non-finite numbers become null."""
    return json_bytes(record.to_json())


def json_bytes(obj: Any) -> bytes:
    """`obj` as compact strict JSON; non-finite numbers become null."""
    try:
        text = json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_scalar)
    except ValueError:  # a NaN or infinity somewhere (a braking cycle): keep the record
        text = json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False, default=_scalar)
    return text.encode()


@dataclass(frozen=True, slots=True)
class ChannelSpec:
    """A channel beside the cycle records: its topic, message encoding and schema (e.g.
    Foxglove's standard ones, daemon.process.scene)."""

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes


_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": None}


class TelemetryRecorder(_Spool[tuple[int, CycleRecord | bytes, int, int]]):
    """Cycle telemetry to an MCAP file (or with `limits` a series of them, each complete
    in itself): one JSON channel, CYCLE_TOPIC, with CYCLE_SCHEMA, and the `channels`
    given (messages already encoded, `log_messages`).

    Each message's log time is the wall-clock time of `record()` (ns) unless given; its
    sequence number counts every call on its channel, so gaps show dropped records (and
    run on from one file of a series to the next).  Messages reach the file a chunk at a
    time (`chunk_size` bytes before compression): a crash loses at most the open chunk.
    `metadata` (e.g. robot name, config file) is stored in every file as the MCAP
    metadata record "cdprd.session"; finishing a file adds "cdprd.recording" with the
    written and dropped counts so far.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        limits: FileLimits | None = None,
        capacity: int = 4096,
        budget: float = 0.0002,
        compression: str = "zstd",
        chunk_size: int = 64 * 1024,
        metadata: Mapping[str, str] | None = None,
        channels: Sequence[ChannelSpec] = (),
    ) -> None:
        if compression not in _COMPRESSION:
            raise ValueError(
                f"telemetry compression {compression!r} is unknown; use one of "
                f"{', '.join(_COMPRESSION)}"
            )
        path = Path(path)
        super().__init__("telemetry recording", path, capacity, budget, limits)
        kind = _COMPRESSION[compression]
        self._compression = CompressionType.NONE if kind is None else kind
        self._chunk_size = chunk_size
        self._metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._specs = tuple(channels)
        # the ids every file gives its channels (MCAP numbers them in registration order)
        self._channel = 1
        self._channels = {spec.topic: 2 + i for i, spec in enumerate(self._specs)}
        self._sequences = dict.fromkeys([self._channel, *self._channels.values()], 0)
        self._begin(path)

    def _open(self, path: Path) -> None:
        _refuse_existing(path, self.kind)
        self._stream: BinaryIO = open(path, "xb")  # noqa: SIM115 - closed in _finish
        try:
            self._writer = self._start_writer()
        except BaseException:
            self._stream.close()
            raise

    def _start_writer(self) -> Writer:
        writer = Writer(self._stream, chunk_size=self._chunk_size, compression=self._compression)
        writer.start(profile="", library="cdprd")
        schema_id = writer.register_schema(
            name=CYCLE_SCHEMA_NAME, encoding="jsonschema", data=json.dumps(CYCLE_SCHEMA).encode()
        )
        channel = writer.register_channel(
            topic=CYCLE_TOPIC,
            message_encoding="json",
            schema_id=schema_id,
            metadata={"schema_version": str(CYCLE_SCHEMA_VERSION)},
        )
        assert channel == self._channel
        if self._metadata:
            writer.add_metadata("cdprd.session", self._metadata)
        for spec in self._specs:
            schema_id = writer.register_schema(
                name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data
            )
            channel = writer.register_channel(
                topic=spec.topic, message_encoding=spec.message_encoding, schema_id=schema_id
            )
            assert channel == self._channels[spec.topic]
        return writer

    def record(self, record: CycleRecord, log_time_ns: int | None = None) -> None:
        """Queue one cycle's record (hot path: no I/O, no encoding; never raises)."""
        self._queue_on(self._channel, record, log_time_ns)

    def log_messages(self, messages: Sequence[tuple[str, bytes]], log_time_ns: int) -> None:
        """Queue encoded messages, each (topic, data) on one of the `channels` given."""
        for topic, data in messages:
            self._queue_on(self._channels[topic], data, log_time_ns)

    def _queue_on(self, channel: int, payload: CycleRecord | bytes, stamp: int | None) -> None:
        sequence = self._sequences[channel]
        self._push((channel, payload, time.time_ns() if stamp is None else stamp, sequence))
        self._sequences[channel] = (sequence + 1) & 0xFFFFFFFF

    def _write(self, item: tuple[int, CycleRecord | bytes, int, int]) -> None:
        channel, payload, stamp, sequence = item
        self._writer.add_message(
            channel_id=channel,
            log_time=stamp,
            data=payload if isinstance(payload, bytes) else encode_cycle(payload),
            publish_time=stamp,
            sequence=sequence,
        )

    def _sync(self) -> None:
        self._stream.flush()

    def _finish(self) -> None:
        try:
            self._writer.add_metadata(
                "cdprd.recording", {"written": str(self.written), "dropped": str(self.dropped)}
            )
            self._writer.finish()
        finally:
            self._stream.close()

    def _abandon(self) -> None:
        self._stream.close()


# -- raw CAN traffic (python-can log formats) ----------------------------------------------

CAN_LOG_SUFFIXES = (".asc", ".blf", ".csv", ".log", ".trc")


def frame_stamp(message: can.Message, rx: bool) -> float:
    """When a frame happened: a received frame's own time if it has one, else now."""
    return message.timestamp if rx and message.timestamp else time.time()


def frame_fields(message: can.Message, rx: bool) -> tuple:
    """A frame as plain values, stamped now (frame_stamp), for a recorder in another
    process (CanRecorder.record_fields)."""
    return (
        frame_stamp(message, rx),
        message.channel,
        message.arbitration_id,
        message.is_extended_id,
        message.is_error_frame,
        message.is_remote_frame,
        message.dlc,
        bytes(message.data),
        rx,
    )


class CanRecorder(_Spool[tuple[can.Message, bool, float]]):
    """Received and sent CAN frames to a python-can log file (or with `limits` a series
    of them); the format follows the suffix (CAN_LOG_SUFFIXES: Vector ASC/BLF, CSV,
    can-utils .log, PCAN TRC), readable with `can.LogReader` and the usual tools.  .csv
    keeps neither direction nor channel.
    `channel` names frames that carry none (frames the driver builds for sending).

    Frames are written in time order.  A received frame carries the time it arrived but
    reaches the recorder only when the loop drains the bus, possibly after a frame the
    daemon sent later; so each frame waits, sorted by time, until a frame stamped
    `reorder` seconds later has been recorded or the file is finished (`written` counts
    frames once sorted)."""

    def __init__(
        self,
        path: str | Path,
        *,
        limits: FileLimits | None = None,
        channel: str | None = None,
        capacity: int = 16384,
        budget: float = 0.0002,
        reorder: float = 0.05,
    ) -> None:
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in CAN_LOG_SUFFIXES:
            raise ValueError(
                f"CAN recording {path}: suffix {suffix or '(none)'!r} is not one of "
                f"{', '.join(CAN_LOG_SUFFIXES)}"
            )
        if not reorder >= 0:
            raise ValueError(f"CAN recording {path}: reorder must be a time >= 0 s, not {reorder}")
        super().__init__("CAN recording", path, capacity, budget, limits)
        self.channel = channel
        self.reorder = reorder
        self._held: list[tuple[float, int, can.Message]] = []  # heap by (time, arrival)
        self._arrival = itertools.count()
        self._newest = -math.inf
        self._begin(path)

    def _open(self, path: Path) -> None:
        _refuse_existing(path, self.kind)
        self._logger = can.Logger(path)

    def record(self, message: can.Message, *, rx: bool, timestamp: float | None = None) -> None:
        """Queue one frame (hot path; never raises).  `rx`: received (True) or sent.
        `timestamp` (s, wall clock like python-can's) defaults to frame_stamp's."""
        if timestamp is None:
            timestamp = frame_stamp(message, rx)
        self._push((message, rx, timestamp))

    def record_fields(self, fields: tuple) -> None:
        """Queue one frame given as frame_fields made it (in another process)."""
        if self.status != "recording":  # paused or stopped: counted, not even built
            self.dropped += 1
            return
        stamp, channel, ident, extended, error, remote, dlc, data, rx = fields
        message = can.Message(
            channel=channel,
            timestamp=stamp,
            arbitration_id=ident,
            is_extended_id=extended,
            is_error_frame=error,
            is_remote_frame=remote,
            dlc=dlc,
            data=data,
            is_rx=rx,
            check=False,
        )
        self.record(message, rx=rx, timestamp=stamp)

    def _write(self, item: tuple[can.Message, bool, float]) -> None:
        message, rx, timestamp = item
        if message.is_rx != rx or message.timestamp != timestamp or message.channel is None:
            message = copy.copy(message)  # the caller's frame stays untouched
            message.is_rx = rx
            message.timestamp = timestamp
            if message.channel is None:
                message.channel = self.channel
        held = self._held
        heapq.heappush(held, (timestamp, next(self._arrival), message))
        self._newest = max(self._newest, timestamp)
        while held and held[0][0] <= self._newest - self.reorder:
            self._logger.on_message_received(heapq.heappop(held)[2])

    def _sync(self) -> None:
        stream = getattr(self._logger, "file", None)
        if stream is not None:
            stream.flush()

    def _finish(self) -> None:
        try:
            while self._held:
                self._logger.on_message_received(heapq.heappop(self._held)[2])
        finally:
            self._logger.stop()

    def _abandon(self) -> None:
        self._held.clear()
        self._logger.stop()
