"""Bus-load accounting for classic CAN (ISO 11898-1) at a configured bitrate.

Bits on the wire per data frame with n data bytes (n = DLC, 0..8), before stuffing:

    standard (11-bit id):  SOF 1, id 11, RTR 1, IDE 1, r0 1, DLC 4, data 8n, CRC 15,
                           CRC delimiter 1, ACK slot 1, ACK delimiter 1, EOF 7, IFS 3
                           = 47 + 8n bits, of which SOF..CRC (34 + 8n) are stuffable;
    extended (29-bit id):  SOF 1, base id 11, SRR 1, IDE 1, id extension 18, RTR 1, r1 1,
                           r0 1, DLC 4, data 8n, CRC 15, then the same 13 unstuffed bits
                           = 67 + 8n bits, of which 54 + 8n are stuffable.

A remote frame has no data field (its DLC is sent, n counts as 0 in the data bits).
Stuffing: after five equal bits the transmitter inserts one of the opposite value, and that
stuff bit counts towards the next run.  Over L stuffable bits:

- worst case  floor((L - 1) / 4): the first stuff bit after 5 bits, then one every 4
  (e.g. 8 data bytes, standard id: 111 + 24 = 135 bits);
- expected    L / 30 for independent uniformly random bits (a Markov chain on the run
  length: the run lengths 1..4 have stationary weights 8, 4, 2, 1 / 15, and a stuff bit
  follows run length 4 with probability 1/2, i.e. 1/30 per bit);
- exact       for a concrete frame: build SOF..CRC (CRC-15/CAN, polynomial 0x4599, init 0,
  over SOF..data), stuff it, count.

An error frame is counted as ERROR_FRAME_BITS = 23: error flag 6, the other nodes'
superposed error flags up to 6, error delimiter 8, intermission 3 (the bits of the frame
it interrupted are not known here).  CAN FD frames are not supported.
"""

from __future__ import annotations

import functools
import re
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

import can

Stuffing = Literal["none", "worst", "expected", "exact"]
STUFFINGS: tuple[str, ...] = ("none", "worst", "expected", "exact")

ERROR_FRAME_BITS = 23
CRC15_POLY = 0x4599
_UNSTUFFED_TAIL = 1 + 1 + 1 + 7 + 3  # CRC delimiter, ACK slot, ACK delimiter, EOF, IFS
_STUFFABLE_HEADER = {False: 1 + 11 + 1 + 1 + 1 + 4, True: 1 + 11 + 1 + 1 + 18 + 1 + 1 + 1 + 4}
_RUNS = re.compile(r"0+|1+")


@dataclass(frozen=True)
class FrameShape:
    """A frame described by its size only (for planning: no data needed)."""

    dlc: int
    extended: bool = False
    remote: bool = False


def _check_dlc(dlc: int) -> None:
    if not isinstance(dlc, int) or not 0 <= dlc <= 8:
        raise ValueError(f"classic CAN data length must be an integer 0..8, got {dlc!r}")


def stuffable_bits(dlc: int, extended: bool = False, remote: bool = False) -> int:
    """Bits from SOF to the end of the CRC field (the part bit stuffing applies to)."""
    _check_dlc(dlc)
    return _STUFFABLE_HEADER[extended] + (0 if remote else 8 * dlc) + 15


def unstuffed_bits(dlc: int, extended: bool = False, remote: bool = False) -> int:
    """Bits of the whole frame including the 3-bit intermission, without stuff bits."""
    return stuffable_bits(dlc, extended, remote) + _UNSTUFFED_TAIL


def worst_case_stuff_bits(dlc: int, extended: bool = False, remote: bool = False) -> int:
    """Most stuff bits any frame of this shape can carry: floor((L - 1) / 4)."""
    return (stuffable_bits(dlc, extended, remote) - 1) // 4


def expected_stuff_bits(dlc: int, extended: bool = False, remote: bool = False) -> float:
    """Mean stuff bits if the stuffable bits were independent and uniform: L / 30."""
    return stuffable_bits(dlc, extended, remote) / 30.0


@functools.lru_cache(maxsize=128, typed=True)  # a few dozen shapes, asked for every frame
def frame_bits(
    dlc: int, extended: bool = False, remote: bool = False, stuffing: Stuffing = "worst"
) -> float:
    """Bits a frame of this shape occupies on the bus ("exact" needs a concrete frame)."""
    base = unstuffed_bits(dlc, extended, remote)
    if stuffing == "none":
        return base
    if stuffing == "worst":
        return base + worst_case_stuff_bits(dlc, extended, remote)
    if stuffing == "expected":
        return base + expected_stuff_bits(dlc, extended, remote)
    raise ValueError(
        f"stuffing {stuffing!r} is not one of 'none', 'worst', 'expected' for a frame shape "
        "('exact' needs a concrete frame: message_bits)"
    )


def crc15(bits: str) -> int:
    """CRC-15/CAN of a bit string ('0'/'1' characters, first transmitted bit first)."""
    crc = 0
    for b in bits:
        top = (crc >> 14) ^ (b == "1")
        crc = (crc << 1) & 0x7FFF
        if top:
            crc ^= CRC15_POLY
    return crc


def frame_bitstream(
    arbitration_id: int, data: bytes, extended: bool = False, remote: bool = False, dlc: int = -1
) -> str:
    """The stuffable part of a data or remote frame, SOF to the end of the CRC, unstuffed.
    `dlc` defaults to len(data) (a remote frame sends a DLC but no data)."""
    if dlc < 0:
        dlc = len(data)
    _check_dlc(dlc)
    if remote:
        data = b""
    elif len(data) != dlc:
        raise ValueError(f"frame 0x{arbitration_id:X}: DLC {dlc} but {len(data)} data bytes")
    rtr = "1" if remote else "0"
    if extended:
        if not 0 <= arbitration_id <= 0x1FFFFFFF:
            raise ValueError(f"extended id 0x{arbitration_id:X} is outside 0..0x1FFFFFFF")
        head = f"0{arbitration_id >> 18:011b}11{arbitration_id & 0x3FFFF:018b}{rtr}00{dlc:04b}"
    else:
        if not 0 <= arbitration_id <= 0x7FF:
            raise ValueError(f"standard id 0x{arbitration_id:X} is outside 0..0x7FF")
        head = f"0{arbitration_id:011b}{rtr}00{dlc:04b}"
    body = head + (format(int.from_bytes(data, "big"), f"0{8 * len(data)}b") if data else "")
    return body + format(crc15(body), "015b")


def stuff(bits: str) -> str:
    """Insert a complementary stuff bit after every five equal bits (bit by bit)."""
    out = []
    run_bit, run = "", 0
    for b in bits:
        out.append(b)
        if b == run_bit:
            run += 1
        else:
            run_bit, run = b, 1
        if run == 5:
            run_bit = "1" if b == "0" else "0"
            out.append(run_bit)
            run = 1
    return "".join(out)


def destuff(bits: str) -> str:
    """Inverse of `stuff`: drop the bit after every five equal bits; ValueError on a
    stuff error (six equal bits) or a missing stuff bit at the end."""
    out = []
    run_bit, run = "", 0
    expect_stuff = False
    for i, b in enumerate(bits):
        if expect_stuff:
            if b == run_bit:
                raise ValueError(f"stuff error at bit {i}: six equal bits")
            run_bit, run, expect_stuff = b, 1, False
            continue
        out.append(b)
        if b == run_bit:
            run += 1
        else:
            run_bit, run = b, 1
        expect_stuff = run == 5
    if expect_stuff:
        raise ValueError("stream ends where a stuff bit is due")
    return "".join(out)


def stuff_bit_count(bits: str) -> int:
    """len(stuff(bits)) - len(bits), computed run by run.  In a run of length L that starts
    with `carry` equal bits already counted (1 when the previous run ended in a stuff bit,
    which has this run's value), the first stuff bit comes after 5 - carry bits and then
    one every 5; the run ends in a stuff bit when that count divides exactly."""
    count, carry = 0, 0
    for match in _RUNS.finditer(bits):
        first = 5 - carry
        length = match.end() - match.start()
        if length < first:
            carry = 0
            continue
        count += 1 + (length - first) // 5
        carry = 1 if (length - first) % 5 == 0 else 0
    return count


def message_bits(msg: can.Message, stuffing: Stuffing = "exact") -> float:
    """Bits `msg` occupies on the bus (error frames: ERROR_FRAME_BITS)."""
    if msg.is_error_frame:
        return ERROR_FRAME_BITS
    if msg.is_fd:
        raise ValueError(f"frame 0x{msg.arbitration_id:X}: CAN FD frames are not supported")
    if stuffing != "exact":
        return frame_bits(msg.dlc, msg.is_extended_id, msg.is_remote_frame, stuffing)
    stream = frame_bitstream(
        msg.arbitration_id, bytes(msg.data), msg.is_extended_id, msg.is_remote_frame, msg.dlc
    )
    return len(stream) + stuff_bit_count(stream) + _UNSTUFFED_TAIL


@dataclass(frozen=True)
class BusLoadReport:
    """Load over the last `window` seconds and totals since the meter started."""

    bitrate: int
    stuffing: str
    window: float
    load: float  # fraction of the window's bit time, 0..(>1 if overloaded)
    window_frames: int
    total_frames: int
    total_error_frames: int
    total_bits: float
    first_timestamp: float | None
    last_timestamp: float | None

    @property
    def mean_load(self) -> float:
        """Total bits over the bit time between the first and last frame (0 before two)."""
        if self.first_timestamp is None or self.last_timestamp is None:
            return 0.0
        span = self.last_timestamp - self.first_timestamp
        return self.total_bits / (self.bitrate * span) if span > 0 else 0.0


class BusLoadMeter:
    """Accumulates frames (by their timestamps) and reports the load fraction over a
    sliding window.  "worst" (default) is the conservative figure to plan with; "exact"
    stuffs every frame (≈ 20 µs each: for analysis, not the 1 kHz hot path)."""

    def __init__(self, bitrate: int, window: float = 1.0, stuffing: Stuffing = "worst") -> None:
        if not isinstance(bitrate, int) or bitrate <= 0:
            raise ValueError(f"bitrate must be a positive integer (bit/s), got {bitrate!r}")
        if not window > 0:
            raise ValueError(f"window must be > 0 seconds, got {window!r}")
        if stuffing not in STUFFINGS:
            raise ValueError(f"stuffing must be one of {STUFFINGS}, got {stuffing!r}")
        self.bitrate = bitrate
        self.window = float(window)
        self.stuffing: Stuffing = stuffing
        self._recent: deque[tuple[float, float]] = deque()
        self._recent_bits = 0.0
        self.total_frames = 0
        self.total_error_frames = 0
        self.total_bits = 0.0
        self.first_timestamp: float | None = None
        self.last_timestamp: float | None = None

    def add(self, msg: can.Message) -> None:
        """Account one frame at msg.timestamp (timestamps must not go backwards much:
        the window is evicted by the newest time seen).  Frames older than the window
        are dropped as new ones come, so that the meter holds one window of frames and
        a report costs little: evicting five seconds of frames at once (~45,000 at
        500 Hz) held the simulator's loop ~9 ms, long enough for the daemon to miss its
        feedback three times running."""
        bits = message_bits(msg, self.stuffing)
        t = msg.timestamp
        self._recent.append((t, bits))
        self._recent_bits += bits
        self.total_frames += 1
        self.total_error_frames += msg.is_error_frame
        self.total_bits += bits
        if self.first_timestamp is None:
            self.first_timestamp = t
        if self.last_timestamp is None or t > self.last_timestamp:
            self.last_timestamp = t
        self._evict(self.last_timestamp)

    def add_many(self, frames: Iterable[can.Message]) -> None:
        for msg in frames:
            self.add(msg)

    def load(self, now: float | None = None) -> float:
        """Fraction of the bit time in (now - window, now] used by frames (now defaults
        to the newest frame's timestamp)."""
        if now is None:
            now = self.last_timestamp if self.last_timestamp is not None else 0.0
        self._evict(now)
        return self._recent_bits / (self.bitrate * self.window)

    def _evict(self, now: float) -> None:
        """Forget the frames at or before now - window."""
        cutoff = now - self.window
        recent = self._recent
        while recent and recent[0][0] <= cutoff:
            self._recent_bits -= recent.popleft()[1]
        if not recent:
            self._recent_bits = 0.0  # no float residue once the window is empty

    def report(self, now: float | None = None) -> BusLoadReport:
        load = self.load(now)
        return BusLoadReport(
            bitrate=self.bitrate,
            stuffing=self.stuffing,
            window=self.window,
            load=load,
            window_frames=len(self._recent),
            total_frames=self.total_frames,
            total_error_frames=self.total_error_frames,
            total_bits=self.total_bits,
            first_timestamp=self.first_timestamp,
            last_timestamp=self.last_timestamp,
        )


@dataclass(frozen=True)
class CycleLoad:
    """Whether one control cycle's frames fit at `rate_hz` (`fits`), and the fastest rate
    at which they would (`max_rate_hz`), given the bus may be loaded up to `max_load`."""

    bits_per_cycle: float
    bitrate: int
    rate_hz: float
    max_load: float
    stuffing: str

    @property
    def bus_time(self) -> float:
        """Seconds of bus time one cycle's frames take."""
        return self.bits_per_cycle / self.bitrate

    @property
    def load(self) -> float:
        return self.bits_per_cycle * self.rate_hz / self.bitrate

    @property
    def fits(self) -> bool:
        return self.load <= self.max_load

    @property
    def max_rate_hz(self) -> float:
        return self.max_load * self.bitrate / self.bits_per_cycle


def cycle_load(
    frames_per_cycle: Sequence[FrameShape | can.Message],
    rate_hz: float,
    bitrate: int,
    stuffing: Stuffing = "worst",
    max_load: float = 1.0,
) -> CycleLoad:
    """Bus load of sending `frames_per_cycle` every 1/rate_hz seconds.  Frame shapes use
    `stuffing` ("exact" is allowed for messages only).  `max_load` < 1 leaves room for the
    time the bus idles while the host computes, and for other traffic."""
    if not isinstance(bitrate, int) or bitrate <= 0:
        raise ValueError(f"bitrate must be a positive integer (bit/s), got {bitrate!r}")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
    if not 0 < max_load <= 1:
        raise ValueError(f"max_load must be in (0, 1], got {max_load!r}")
    if not frames_per_cycle:
        raise ValueError("frames_per_cycle is empty")
    bits = 0.0
    for frame in frames_per_cycle:
        if isinstance(frame, can.Message):
            bits += message_bits(frame, stuffing)
        else:
            bits += frame_bits(frame.dlc, frame.extended, frame.remote, stuffing)
    return CycleLoad(bits, bitrate, float(rate_hz), float(max_load), stuffing)
