"""The actuator-driver interface the daemon and the simulator program against.

A driver is the HOST side of one drive protocol for all actuators on one bus: it turns
force commands into frames, frames into lengths, rates and drive status, and knows the
protocol's start-up, enable, disable and brake sequences.  Every protocol also has a
DEVICE side (`VirtualDrive`), the drive's own behaviour, which the simulator runs.

Sans-IO: the hot path (`cycle_start`, `commands`, `receive`) is synchronous and returns
or consumes `can.Message` objects; only sequences that must wait for a drive's answer
(start-up, enable, fault reset) are coroutines, and they talk to the bus through a
`Link` that the caller provides.  Nothing here opens a bus or sleeps on a timer.
"""

from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import can

from cdpr.spool import Spool


class DriverError(RuntimeError):
    """A drive did not do what the protocol asked of it (names the node and the step)."""


class FrameError(ValueError):
    """A malformed frame (wrong length, non-finite or out-of-range value); the message
    names the frame id and the problem.  Counted and dropped, never acted on."""


_new_message = can.Message.__new__


def bus_frame(
    can_id: int,
    data: bytes | bytearray = b"",
    *,
    timestamp: float = 0.0,
    channel: str | None = None,
    extended: bool = False,
    remote: bool = False,
    error: bool = False,
    dlc: int | None = None,
) -> can.Message:
    """A classic CAN frame, the same as can.Message(timestamp=..., arbitration_id=can_id,
    is_extended_id=extended, is_remote_frame=remote, is_error_frame=error, channel=...,
    dlc=dlc, data=data, check=False), built ~4x cheaper by setting its fields directly
    (the constructor's generic argument handling is most of its cost, and every frame a
    cycle sends or receives is one; tests/drivers/test_data_frame.py keeps the two equal
    field by field).  `dlc` None: the data's length.  The frame owns a copy of `data`."""
    frame = _new_message(can.Message)
    frame.timestamp = timestamp
    frame.arbitration_id = can_id
    frame.is_extended_id = extended
    frame.is_remote_frame = remote
    frame.is_error_frame = error
    frame.channel = channel
    frame.is_fd = False
    frame.is_rx = True
    frame.bitrate_switch = False
    frame.error_state_indicator = False
    frame.data = bytearray(data)
    frame.dlc = len(data) if dlc is None else dlc
    return frame


def data_frame(can_id: int, data: bytes | bytearray = b"") -> can.Message:
    """A standard-id data frame: bus_frame's, as can.Message(arbitration_id=can_id,
    data=data, is_extended_id=False) builds it."""
    return bus_frame(can_id, data)


class Timing(enum.Enum):
    """Who clocks the cycle.  SYNC: the host sends a SYNC frame and every drive answers
    with its feedback.  CYCLIC: drives stream feedback at their own configured rate and
    the host's timer runs the cycle on the newest sample."""

    SYNC = "sync"
    CYCLIC = "cyclic"


class BrakeMode(enum.Enum):
    """How a drive freezes its cable length (DESIGN §9).  Never a bare "motor off":
    POSITION_HOLD servoes the drive at the length it had when braking started;
    HOLDING_BRAKE engages the drive's mechanical brake (then disables the power stage)."""

    POSITION_HOLD = "position_hold"
    HOLDING_BRAKE = "holding_brake"


class DriveState(enum.Enum):
    """A drive's state as the host last saw it, common to every protocol."""

    UNKNOWN = "unknown"  # nothing heard yet
    DISABLED = "disabled"  # power stage off (brake engaged if the drive has one)
    READY = "ready"  # powered, not producing torque (402: switched on; ODrive: idle)
    ENABLED = "enabled"  # following force commands
    HOLDING = "holding"  # braked by position hold or holding brake
    FAULT = "fault"  # the drive reports a fault


@dataclass(frozen=True)
class Scaling:
    """Drive units <-> cable units for one actuator.

    Positive cable length change pays cable out (DESIGN §3); `direction` is +1 when a
    positive motor rotation pays cable out, -1 otherwise.  `counts_per_rev` is encoder
    increments per MOTOR revolution (1.0 for drives that report turns); `gear_ratio`
    motor revolutions per drum revolution; `length_offset` the cable length (m) at
    motor position 0.  Forces are along +l (N), motor torques in N·m at the motor shaft.
    With a `spool` (cdpr.spool) the drum's radius follows the cable length: rates,
    velocities, torques and forces then convert at a cable length (`length`, m).
    """

    drum_radius: float
    gear_ratio: float = 1.0
    counts_per_rev: float = 1.0
    direction: int = 1
    length_offset: float = 0.0
    spool: Spool | None = None
    _zero_angle: float = field(init=False, repr=False, compare=False, default=0.0)
    # the per-count factors, computed once: every feedback frame converts with them
    _metres_per_count: float = field(init=False, repr=False, compare=False, default=0.0)
    _radians_per_count: float = field(init=False, repr=False, compare=False, default=0.0)

    def __post_init__(self) -> None:
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, not {self.direction}")
        for name in ("drum_radius", "gear_ratio", "counts_per_rev"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, not {value}")
        per_rev = self.gear_ratio * self.counts_per_rev
        metres = self.direction * 2.0 * math.pi * self.drum_radius / per_rev
        object.__setattr__(self, "_metres_per_count", metres)
        object.__setattr__(self, "_radians_per_count", self.direction * 2.0 * math.pi / per_rev)
        if self.spool is not None:  # the wound angle at motor position 0
            object.__setattr__(self, "_zero_angle", self.spool.angle(self.length_offset))

    @property
    def metres_per_count(self) -> float:
        """Cable length per encoder increment at drum_radius, signed by `direction`."""
        return self._metres_per_count

    @property
    def radians_per_count(self) -> float:
        """Drum angle paid out per encoder increment, signed by `direction`."""
        return self._radians_per_count

    def radius(self, length: float | None = None) -> float:
        """The drum's effective radius (m): drum_radius, or the spool's at cable length
        `length` (ValueError without it)."""
        if self.spool is None:
            return self.drum_radius
        if length is None:
            raise ValueError("a drum with a spool converts at a cable length: give `length`")
        return self.spool.radius_at(length)

    def length(self, position: float) -> float:
        """Cable length (m) from a motor position in encoder increments."""
        if self.spool is None:
            return self.length_offset + position * self._metres_per_count
        return self.spool.length(self._zero_angle - position * self._radians_per_count)

    def position(self, length: float) -> float:
        """Motor position (increments, not rounded) at cable length `length`."""
        if self.spool is None:
            return (length - self.length_offset) / self.metres_per_count
        return (self._zero_angle - self.spool.angle(length)) / self.radians_per_count

    def rate(self, velocity: float, length: float | None = None) -> float:
        """Cable rate (m/s) from a motor velocity in increments per second."""
        if self.spool is None:
            return velocity * self._metres_per_count
        return velocity * self._radians_per_count * self.radius(length)

    def velocity(self, rate: float, length: float | None = None) -> float:
        """Motor velocity (increments/s) at cable rate `rate`."""
        if self.spool is None:
            return rate / self.metres_per_count
        return rate / (self.radians_per_count * self.radius(length))

    def motor_torque(self, force: float, length: float | None = None) -> float:
        """Motor torque (N·m) producing force `force` along +l (lossless gearing)."""
        return self.direction * force * self.radius(length) / self.gear_ratio

    def force(self, torque: float, length: float | None = None) -> float:
        """Force along +l (N) from a motor torque (N·m)."""
        return self.direction * torque * self.gear_ratio / self.radius(length)


@dataclass
class Feedback:
    """The newest feedback of one actuator.  `stamp` is the host's monotonic receive
    time (s), `count` increments with every accepted feedback frame, so a cycle can
    tell fresh feedback from stale.  Timing.SYNC drivers: `latched` is the host's
    monotonic time of the SYNC the sample answers (when the drive latched it); `first`
    and `second` the lengths of the first answer to one SYNC and of a second one,
    dropped (the pair that disagrees most); the cycle that judges them sets them back to
    NaN (none)."""

    length: float = math.nan
    rate: float = math.nan
    stamp: float = -math.inf
    latched: float = -math.inf
    count: int = 0
    first: float = math.nan
    second: float = math.nan


@dataclass
class NodeStatus:
    """Protocol-independent health of one drive, as the host last heard it."""

    state: DriveState = DriveState.UNKNOWN
    fault: str | None = None  # readable fault text while the drive reports one
    fault_code: int = 0  # the protocol's code (402: EMCY error code; ODrive: axis error)
    heartbeat_stamp: float = -math.inf  # monotonic time of the last heartbeat
    restarts: int = 0  # restarts seen since start (402 boot-up): position from a new zero
    # whether the drive's own answer shows that the standing brake holds it: None while
    # unknown (or no brake stands), True confirmed, False with `hold_problem` saying why
    held: bool | None = None
    hold_problem: str | None = None


@dataclass
class FrameCounters:
    """Frames the driver took in: accepted, and rejected by reason (for diagnostics;
    a rejected frame is never acted on)."""

    accepted: int = 0
    rejected: Counter[str] = field(default_factory=Counter)

    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


class Link(Protocol):
    """The bus as start-up sequences see it: the daemon (or a test) provides it."""

    def send(self, message: can.Message) -> None:
        """Queue `message` for transmission."""
        ...

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        """The next received frame for which `match` is true; raise DriverError naming
        `what` if none arrives within `timeout` seconds.  Every frame still reaches
        the driver's `receive`."""
        ...


class ActuatorDriver(ABC):
    """Host side of one protocol for the n actuators on one bus, in cable order.

    `feedback[i]` and `status[i]` are updated by `receive`; the daemon reads them.
    """

    timing: Timing

    def __init__(self, scalings: Sequence[Scaling]) -> None:
        self.scalings = list(scalings)
        self.n = len(self.scalings)
        self.feedback = [Feedback() for _ in range(self.n)]
        self.status = [NodeStatus() for _ in range(self.n)]
        self.counters = FrameCounters()

    # -- sequences that wait for the drives ------------------------------------------

    @abstractmethod
    async def start(self, link: Link, now: Callable[[], float]) -> None:
        """Bring every drive from power-on to READY with its power stage off and its
        brake engaged: boot-up/heartbeat seen, configuration written, watchdogs armed.
        Raises DriverError naming the node and the step that failed."""

    @abstractmethod
    async def enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
        """Move every drive to ENABLED.  `lengths` (m, current) lets a drive hold its
        position where the protocol passes through a position mode on the way; from the
        moment it follows force commands it produces `forces` (N along +l: the tensions
        holding the platform at rest, f = -t) until the first cycle's command, so
        enabling never drops the load."""

    @abstractmethod
    async def reset_faults(self, link: Link) -> None:
        """Clear latched drive faults; the drives end READY or HOLDING, never moving."""

    @property
    def measures_force(self) -> bool:
        """Whether `measured_forces` can read the drives' own force measurement."""
        return False

    async def measured_forces(self, link: Link) -> list[float]:
        """Each drive's force now (N along +l) as the drive itself measures it (its
        current sensing), read while it holds a position: at rest, the cables' tensions
        (f = -t) and the drums' friction.  DriverError naming the node if a drive does
        not answer, or if the drives offer no such reading (`measures_force`)."""
        raise DriverError("the drives offer no force measurement")

    # -- immediate frames (safe to call from the cycle and from fault handlers) -------

    @abstractmethod
    def cycle_start(self) -> list[can.Message]:
        """Frames that open a cycle (402: SYNC; cyclic drives: none)."""

    @abstractmethod
    def commands(self, forces: Sequence[float]) -> list[can.Message]:
        """The force commands of one cycle (N along +l per actuator), one or more frames
        per drive; a command also feeds the drive's watchdog.  Raises FrameError on a
        non-finite force (the caller brakes instead)."""

    @abstractmethod
    def brake(self, lengths: Sequence[float], mode: BrakeMode) -> list[can.Message]:
        """Frames that freeze every cable at `lengths` (m) by `mode`.  Must not need an
        answer to take effect.  `lengths` are trusted (daemon.service.trusted_lengths), never a
        raw frame's value; NaN where none is trusted, and the driver then holds the drive
        without a target of its own choosing (its own estimate, or power stage off)."""

    @abstractmethod
    def disable(self) -> list[can.Message]:
        """Frames that switch every power stage off (brakes engage where fitted).
        Only for a platform that is resting or held by brakes."""

    @abstractmethod
    def keepalive(self) -> list[can.Message]:
        """Frames sent every cycle while not commanding force (e.g. re-sent position
        hold, watchdog feed), so drive-side watchdogs stay armed but fed."""

    # -- input --------------------------------------------------------------------------

    @abstractmethod
    def receive_ids(self) -> frozenset[int]:
        """The standard (11-bit) ids of every frame this driver reads, in the cycle and
        in its start, enable and reset sequences: the bus may drop all others (and every
        extended frame) before they reach the daemon."""

    @abstractmethod
    def receive(self, message: can.Message, now: float) -> int | None:
        """Decode one received frame, which reached the host at `now` (the daemon's
        monotonic clock).  Returns the actuator index whose feedback this
        frame refreshed, else None.  Frames for other nodes or protocols are ignored;
        malformed frames for this driver's nodes are counted in `counters.rejected`
        (never raised, never acted on)."""


class Actuation(enum.Enum):
    """What a simulated drive's power stage does to its winch."""

    OFF = "off"  # no torque; the drum free-wheels unless the brake is engaged
    TORQUE = "torque"  # produce `VirtualDrive.force` along +l
    POSITION = "position"  # servo to `VirtualDrive.target_length`, plus `force` feed-forward


def _unheeded() -> None:
    """No simulator routes this drive's frames yet."""


class VirtualDrive(ABC):
    """Device side of one drive, for the simulator: the drive's state machine,
    watchdog and heartbeat, answering frames as the real drive would.

    The simulator calls `measure` with the winch's true drum length and rate every
    plant step, `on_frame` for every frame on the bus it `hears`, and `on_tick` at least every
    millisecond; it applies `actuation`, `force`, `target_length` and `brake_engaged`
    to the winch.  `glitch` (m) is added to the length the drive reports, in its
    feedback frames only: a corrupted feedback channel; its own position loop keeps
    the true encoder.
    """

    def __init__(self, node_id: int, scaling: Scaling) -> None:
        self.node_id = node_id
        self.scaling = scaling
        self.actuation = Actuation.OFF
        self.force = 0.0  # N along +l: with TORQUE the force, with POSITION a feed-forward
        self.target_length = math.nan  # m, with Actuation.POSITION
        self.brake_engaged = True  # holding brakes are fail-safe: on while unpowered
        # N along +l: what the power stage produced in the last step, as the drive's own
        # current measurement reports it (CiA 402 torque actual 0x6077); 0 while off
        self.produced = 0.0
        self.length = 0.0  # m, the encoder's view, set by measure()
        self.rate = 0.0
        self.glitch = 0.0  # m added to the reported length (a fault the simulator injects)
        # called when the set of CAN ids `hears` accepts changes (the simulator's routes)
        self.routes_changed: Callable[[], None] = _unheeded

    def hears(self, can_id: int) -> bool:
        """Whether a frame of this standard `can_id` can concern the drive (its simulator
        hands it no others; default: every frame).  A drive whose answer changes calls
        `routes_changed()`."""
        return True

    def measure(self, length: float, rate: float) -> None:
        """The winch's drum length (m) and rate (m/s) as the drive's encoder sees them."""
        self.length = length
        self.rate = rate

    @abstractmethod
    def on_frame(self, message: can.Message, now: float) -> list[can.Message]:
        """React to one frame seen on the bus; returns the frames the drive sends."""

    @abstractmethod
    def on_tick(self, now: float) -> list[can.Message]:
        """Time passes: heartbeats, cyclic feedback, watchdog expiry."""

    @abstractmethod
    def inject_fault(self, code: int, text: str) -> list[can.Message]:
        """The drive detects an internal fault: it brakes as configured and reports it
        (402: EMCY + fault state; ODrive: axis error in the heartbeat)."""
