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
loop thread gets it back, longer than a 1 kHz cycle.  A write error (disk full, …) is
logged once and ends the recording; it never reaches the cycle.

Values are read when written, not when recorded: hand `record()` objects the cycle does
not modify afterwards (tuples, lists from `.tolist()`, or freshly allocated arrays).

A recorder never overwrites a file (the recording of the run before a watchdog restart is
the evidence of why it stalled): name each run's file with `session_path`.
"""

from __future__ import annotations

import asyncio
import copy
import datetime
import heapq
import itertools
import json
import logging
import math
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Generic, Self, TypeVar

import can
from mcap.writer import CompressionType, Writer

log = logging.getLogger(__name__)

Item = TypeVar("Item")


def session_path(path: str | Path, start: datetime.datetime | None = None) -> Path:
    """`path` with the start time inserted before the suffix ("cycle.mcap" ->
    "cycle-20250102-030405.mcap", local time), plus "-2", "-3", … if that file exists."""
    path = Path(path)
    stamp = (start or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    candidate = path.with_name(f"{path.stem}-{stamp}{path.suffix}")
    n = 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}-{stamp}-{n}{path.suffix}")
    return candidate


def _refuse_existing(path: Path, what: str) -> None:
    if path.exists():
        raise FileExistsError(f"{what} {path} exists; recordings are never overwritten")


class _Spool(ABC, Generic[Item]):
    """A bounded queue filled by the cycle and written out by `flush`/`run`."""

    def __init__(self, what: str, capacity: int, budget: float) -> None:
        if capacity < 1:
            raise ValueError(f"{what}: capacity must be at least 1, not {capacity}")
        if not budget >= 0:
            raise ValueError(f"{what}: budget must be a non-negative time (s), not {budget}")
        self._what = what
        self.capacity = capacity
        self.budget = budget
        self._queue: deque[Item] = deque()
        self.dropped = 0  # records lost: queue full, or recorder failed or closed
        self.written = 0
        self.failed: str | None = None  # why writing stopped, if it did
        self.closed = False

    @property
    def pending(self) -> int:
        """Records queued and not yet written."""
        return len(self._queue)

    def _push(self, item: Item) -> None:
        if self.closed or self.failed is not None or len(self._queue) >= self.capacity:
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
            self._fail(exc)
        self.written += count
        return count

    async def run(self, period: float = 0.05) -> None:
        """Write the queue out every `period` seconds, yielding to the loop after each
        `budget` of writing, until the recorder is closed or fails.  Cancel the task, then
        call `close()`."""
        if not period > 0:
            raise ValueError(f"{self._what}: period must be positive, not {period}")
        while not self.closed and self.failed is None:
            await asyncio.sleep(period)
            while self._queue and self.failed is None and not self.closed:
                self.flush(self.budget)
                await asyncio.sleep(0)

    def close(self) -> None:
        """Write what is queued, finish the file and stop accepting records."""
        if self.closed:
            return
        if self.failed is None:
            self.flush()
        self.closed = True
        try:
            self._finish()
        except Exception as exc:
            self._fail(exc)
        if self.dropped:
            log.warning("%s incomplete: %d records dropped", self._what, self.dropped)

    def _fail(self, exc: Exception) -> None:
        if self.failed is None:
            log.error("%s stopped: %s: %s", self._what, type(exc).__name__, exc)
            self.failed = f"{type(exc).__name__}: {exc}"
        self.dropped += len(self._queue)
        self._queue.clear()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abstractmethod
    def _write(self, item: Item) -> None:
        """Encode and write one record."""

    @abstractmethod
    def _sync(self) -> None:
        """Push written records towards the disk after a pass."""

    @abstractmethod
    def _finish(self) -> None:
        """Complete and close the file."""


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
    """Cycle telemetry to an MCAP file: one JSON channel, CYCLE_TOPIC, with CYCLE_SCHEMA,
    and the `channels` given (messages already encoded, `log_messages`).

    Each message's log time is the wall-clock time of `record()` (ns) unless given; its
    sequence number counts every call on its channel, so gaps show dropped records.
    Messages reach the file a chunk at a time (`chunk_size` bytes before compression):
    a crash loses at most the open chunk.  `metadata` (e.g. robot name, config file) is
    stored as the MCAP metadata record "cdprd.session"; `close()` adds "cdprd.recording"
    with the written and dropped counts.
    """

    def __init__(
        self,
        path: str | Path,
        *,
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
        super().__init__(f"telemetry recording {path}", capacity, budget)
        self.path = Path(path)
        _refuse_existing(self.path, "telemetry recording")
        self._stream: BinaryIO = open(self.path, "xb")  # noqa: SIM115 - closed in _finish
        try:
            self._writer, self._channel = self._start(compression, chunk_size, metadata)
            self._channels = {spec.topic: self._register(spec) for spec in channels}
        except BaseException:
            self._stream.close()
            raise
        self._sequences = dict.fromkeys([self._channel, *self._channels.values()], 0)

    def _start(
        self, compression: str, chunk_size: int, metadata: Mapping[str, str] | None
    ) -> tuple[Writer, int]:
        kind = _COMPRESSION[compression]
        writer = Writer(
            self._stream,
            chunk_size=chunk_size,
            compression=CompressionType.NONE if kind is None else kind,
        )
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
        if metadata:
            writer.add_metadata("cdprd.session", {str(k): str(v) for k, v in metadata.items()})
        return writer, channel

    def _register(self, spec: ChannelSpec) -> int:
        schema_id = self._writer.register_schema(
            name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data
        )
        return self._writer.register_channel(
            topic=spec.topic, message_encoding=spec.message_encoding, schema_id=schema_id
        )

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
    """Received and sent CAN frames to a python-can log file; the format follows the
    suffix (CAN_LOG_SUFFIXES: Vector ASC/BLF, CSV, can-utils .log, PCAN TRC), readable
    with `can.LogReader` and the usual tools.  .csv keeps neither direction nor channel.
    `channel` names frames that carry none (frames the driver builds for sending).

    Frames are written in time order.  A received frame carries the time it arrived but
    reaches the recorder only when the loop drains the bus, possibly after a frame the
    daemon sent later; so each frame waits, sorted by time, until a frame stamped
    `reorder` seconds later has been recorded or the file is closed (`written` counts
    frames once sorted)."""

    def __init__(
        self,
        path: str | Path,
        *,
        channel: str | None = None,
        capacity: int = 16384,
        budget: float = 0.0002,
        reorder: float = 0.05,
    ) -> None:
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in CAN_LOG_SUFFIXES:
            raise ValueError(
                f"CAN recording {self.path}: suffix {suffix or '(none)'!r} is not one of "
                f"{', '.join(CAN_LOG_SUFFIXES)}"
            )
        if not reorder >= 0:
            raise ValueError(f"CAN recording {path}: reorder must be a time >= 0 s, not {reorder}")
        super().__init__(f"CAN recording {path}", capacity, budget)
        self.channel = channel
        self.reorder = reorder
        self._held: list[tuple[float, int, can.Message]] = []  # heap by (time, arrival)
        self._arrival = itertools.count()
        self._newest = -math.inf
        _refuse_existing(self.path, "CAN recording")
        self._logger = can.Logger(self.path)

    def record(self, message: can.Message, *, rx: bool, timestamp: float | None = None) -> None:
        """Queue one frame (hot path; never raises).  `rx`: received (True) or sent.
        `timestamp` (s, wall clock like python-can's) defaults to frame_stamp's."""
        if timestamp is None:
            timestamp = frame_stamp(message, rx)
        self._push((message, rx, timestamp))

    def record_fields(self, fields: tuple) -> None:
        """Queue one frame given as frame_fields made it (in another process)."""
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
