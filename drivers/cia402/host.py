"""Host side of CiA 402 drives in cyclic synchronous torque (CST) mode on one CANopen bus.

The drive profile (drives.profile, checked against the EDS by drivers.cia402.profile)
says which PDOs carry what; the defaults are codec.RPDO1/RPDO2/TPDO1/TPDO2.  In the
compact layout (profile.py) one shared RPDO carries the target torques of every drive of
the bus, controlword and mode go in each drive's control RPDO only when they change (the
first torque command after a hold, brake, enable or SDO controlword), the statusword comes
in an event-driven TPDO, and without velocity actual the rate is the difference of the
last two samples' lengths over the time between their SYNCs.

Cycle (Timing.SYNC): `cycle_start` sends SYNC (and the host's heartbeat every
host_heartbeat_period, also between SDO requests); every drive answers with its TPDOs.
`receive` returns a cable's index when the last of a drive's TPDOs on SYNC since the
latest SYNC arrives: feedback is complete for the cycle (and the drive alive).  A TPDO
on SYNC after its drive's sample was complete is counted as rejected and dropped (one
repeated within the sample replaces the earlier one).  Either is a second answer to one
SYNC: on a bus never legitimate (another node sends this node's PDOs: a node-id conflict
or a forger), but over relays on a loaded host a late answer to the SYNC before can land
after the latest one.  So one carrying a position records its length beside the one
already received (Feedback.first / second: the pair that disagrees most, until the
daemon's cycle judges it, daemon.service.trusted_lengths).  Event-driven TPDOs update
the state.  A mode of operation display other than 8 or 10
while operation is enabled is a drive FAULT (reported, the frame still counts).
`commands` sends one torque RPDO per drive (controlword "enable operation", target
torque in per mille of the rated torque, mode 10), or the shared one.

Torque: force f (N along +l) -> motor torque Scaling.motor_torque(f) -> per mille of
`rated_torque`, rounded to the nearest per mille and clamped to +- the drive's max
torque 0x6072 (read at start-up after the profile's writes, EDS default before); clamps
are counted in `torque_limited`.  A non-finite force raises FrameError (the caller
brakes instead).

Brake (DESIGN §9; never a quick stop, which only ramps torque to zero and lets a
suspended platform fall):
- POSITION_HOLD: the hold RPDO (default RPDO2) with "enable operation", mode 8 (cyclic
  synchronous position) and the current length as target position; one frame per drive,
  acted on at reception.
  The lengths are the host's trusted ones (never a raw frame's value, which may be
  forged): a non-finite or out-of-range one means none is trusted for that drive, which
  was then never enabled by this host, and it gets the power-stage-off frame below.
- HOLDING_BRAKE: the torque RPDO with "disable operation" (OPERATION ENABLED -> SWITCHED ON), zero
  torque: the drive engages its holding brake as its power stage goes off.  Asked of a
  bus whose drives have no holding brake, brake() holds position instead.
`brake` never raises and needs no answer; `keepalive` repeats the latest brake, disable or
enable frames each cycle (a lost frame is made good at the next one).

Start-up (SDO, expedited and segmented, own small client since canopen's blocks on a
thread), per drive: statusword read first; device type checked; NMT pre-operational only
for a drive that holds no load (not OPERATION ENABLED, QUICK STOP ACTIVE or latched);
the PDO mapping read back and, where it differs from the profile's, written by the CiA
301 procedure (COB-ID bit 31 set, sub0 = 0, entries, sub0, COB-ID valid) and read back
again; the EDS's other PDOs switched off; rated torque checked against the config; then
the plan's writes (SYNC COB-ID, heartbeat 0x1017, the drive's consumer of the host
heartbeat 0x1016, abort connection option 0x6007 = quick stop, quick stop option 0x605A
= hold, every mapped RPDO's deadline 0x14xx:05 off where the EDS has it: the host sends
no RPDO every cycle in every state, and a drive times each RPDO apart; then the profile's
sdo_writes).  NMT start, operational heartbeats awaited, and the 402 machine driven to
SWITCHED ON.  A drive found in FAULT or QUICK STOP ACTIVE is left as it is (it holds by
its own reaction).  A drive found OPERATION ENABLED is taken over without a torque step:
its mode, position and target torque are read, and the host keeps sending what it does
(the same torque in mode 10, else a hold at its actual position in mode 8) until
enable() or brake() says otherwise.  The cyclic path never uses SDO.
"""

from __future__ import annotations

import contextlib
import math
import struct
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from itertools import pairwise
from operator import itemgetter

import can

from drivers.base import (
    ActuatorDriver,
    BrakeMode,
    DriverError,
    DriveState,
    FrameError,
    Link,
    Scaling,
    Timing,
    data_frame,
)
from drivers.cia402.codec import (
    CONTROLWORD,
    DEVICE_PROFILE_402,
    DEVICE_TYPE,
    EMCY_BASE,
    ERROR_CODE,
    HEARTBEAT_BASE,
    HEARTBEAT_LOST,
    I32_MAX,
    I32_MIN,
    MAX_TORQUE,
    MODE_DISPLAY,
    MODE_OF_OPERATION,
    PDO_INVALID,
    POSITION_ACTUAL,
    RATED_TORQUE,
    SDO_RESPONSE_BASE,
    STATUSWORD,
    TARGET_POSITION,
    TARGET_TORQUE,
    TORQUE_ACTUAL,
    VELOCITY_ACTUAL,
    Cia402FrameError,
    NmtCommand,
    NmtState,
    PdoLayout,
    SdoKind,
    abort_text,
    decode_emcy,
    decode_heartbeat,
    decode_sdo_response,
    emcy_text,
    encode_heartbeat,
    encode_nmt,
    encode_sdo_download_initiate,
    encode_sdo_download_request,
    encode_sdo_segment,
    encode_sdo_segment_ask,
    encode_sdo_upload_request,
    encode_sync,
    od_value,
    od_variable,
)
from drivers.cia402.hold_check import HoldCheck
from drivers.cia402.profile import DrivePlan, SdoStep, plan
from drivers.cia402.statemachine import (
    CONTROL_RELEASE_HOLD,
    DISABLE_OPERATION,
    MODE_CSP,
    MODE_CST,
    MODES,
    STATUS_HOLD,
    Command,
    State,
    decode_statusword,
    drive_state,
)
from drivers.config import DrivesConfig

_FAULTED = (State.FAULT, State.FAULT_REACTION_ACTIVE)
_ENABLE = Command.ENABLE_OPERATION.value
_HOLDING = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)
_FEEDBACK = (STATUSWORD, POSITION_ACTUAL, VELOCITY_ACTUAL, MODE_DISPLAY)
_isfinite = math.isfinite


def _packer(layout: PdoLayout, target: int) -> Callable[[int, int, int], bytes]:
    """pack(controlword, target value, mode) for an RPDO mapping controlword, `target`
    and the mode in any order (other mapped objects are sent as 0)."""
    order = (CONTROLWORD, target, MODE_OF_OPERATION)
    slots = [order.index(e.index) if e.index in order else 3 for e in layout.entries]
    pack = layout.struct.pack
    if slots == [0, 1, 2]:  # mapped in pack's own order (codec.RPDO1, RPDO2): as it is
        return pack
    if len(slots) == 1:  # itemgetter of one item gives the item, not a tuple
        (slot,) = slots
        return lambda controlword, value, mode: pack((controlword, value, mode, 0)[slot])
    pick = itemgetter(*slots)
    return lambda controlword, value, mode: pack(*pick((controlword, value, mode, 0)))


def _torque_frames(layout: PdoLayout, nodes: Sequence[int]) -> Callable[[list[int]], list]:
    """frames(torques, per mille) of the torque RPDO: one shared frame for the bus, or
    one frame per drive with "enable operation" and mode 10."""
    if layout.slots > 1:
        cob, pack = layout.cob_id(nodes[0]), layout.struct.pack
        return lambda torques: [data_frame(cob, pack(*torques))]
    ids, pack = [layout.cob_id(node) for node in nodes], _packer(layout, TARGET_TORQUE)
    return lambda torques: [
        data_frame(can_id, pack(_ENABLE, torque, MODE_CST))
        for can_id, torque in zip(ids, torques, strict=True)
    ]


class Cia402Driver(ActuatorDriver):
    """All CiA 402 drives of one bus, in cable order (`config.nodes[i]` drives cable i)."""

    timing = Timing.SYNC
    sdo_timeout = 0.3  # s to wait for each SDO answer: the canopen package's default
    # ... but after a brake, a drive that does not answer may be STOPPED in torque: the
    # hold check moves on to bring it back after this, not the sequences' patience
    hold_check_timeout = 0.1
    state_polls = 100  # statusword reads while waiting for one 402 transition
    enable_timeout = 1.0  # s for every drive to report OPERATION ENABLED after enable()

    def __init__(
        self, config: DrivesConfig, scalings: Sequence[Scaling], setup: DrivePlan | None = None
    ) -> None:
        if config.protocol != "cia402":
            raise ValueError(f"Cia402Driver needs protocol cia402, config says {config.protocol}")
        super().__init__(scalings)
        if len(config.nodes) != self.n:
            raise ValueError(f"{self.n} scalings for {len(config.nodes)} drives")
        self.config = config
        self.nodes = list(config.nodes)
        self.plan = setup if setup is not None else plan(config)
        self.eds = self.plan.eds
        self.od = self.plan.od
        self.clock: Callable[[], float] = time.monotonic  # paces the host heartbeat (start sets it)
        self._heartbeat = encode_heartbeat(config.profile.host_node, NmtState.OPERATIONAL)
        self._heartbeat_period, self._consumer_time = config.host_heartbeat()
        self._next_heartbeat = -math.inf
        # when the latest heartbeats went out, enough to span two consumer times: what a
        # drive's "heartbeat lost" is judged against (_host_silence)
        kept = math.ceil(2 * self._consumer_time / self._heartbeat_period) + 2
        self._heartbeats_sent: deque[float] = deque(maxlen=kept)
        rated = config.rated_torque
        assert rated is not None  # DrivesConfig requires it for cia402
        # per mille of rated torque per newton along +l, per cable (a drum with a spool:
        # at its latest length, _on_tpdo)
        self._permille = [
            s.motor_torque(1.0, s.length_offset) / rated * 1000.0 for s in self.scalings
        ]
        self.max_torque = [int(od_value(od_variable(self.od, MAX_TORQUE)))] * self.n
        self.torque_limited = [0] * self.n  # commands clamped to +-max_torque
        self.nmt_state: list[NmtState | None] = [None] * self.n
        self._started = [False] * self.n
        # a started drive left OPERATIONAL (boot-up or NMT change): it lost its
        # configuration and, after a reboot, its position; a FAULT until start() again
        self._lost = [False] * self.n
        torque, hold = self.plan.torque, self.plan.hold
        self._torque_pack = _packer(torque, TARGET_TORQUE)
        self._torque_frames = _torque_frames(torque, self.nodes)
        self._shared = torque.slots > 1
        self._hold_pack = _packer(hold, TARGET_POSITION)
        self._rpdo1 = [torque.cob_id(node) for node in self.nodes]  # torque RPDO ids
        self._rpdo2 = [hold.cob_id(node) for node in self.nodes]  # hold RPDO ids
        # controlword and mode: in the torque RPDO, or in the control RPDO, sent when
        # they change: `_in_torque` says the drive was told "enable operation" in mode 10
        control = self.plan.control or torque
        self._control = self.plan.control is not None
        self._cw_pack = _packer(control, TARGET_TORQUE)
        self._cw_ids = [control.cob_id(node) for node in self.nodes]
        self._in_torque = [False] * self.n
        self._held = [0] * self.n  # target torques of drives taken over in mode 10
        self._routes: dict[int, tuple[Callable[[int, int, bytearray, float], int | None], int]] = {}
        # TPDO id -> (bit in the sample, 0 for an event-driven TPDO; name, struct, slot
        # of each _FEEDBACK object or -1)
        self._tpdo: dict[int, tuple[int, str, struct.Struct, tuple[int, ...]]] = {}
        synced = [layout for layout in self.plan.tpdos if layout.on_sync]
        for i, node in enumerate(self.nodes):
            for layout in self.plan.tpdos:
                bit = 1 << synced.index(layout) if layout.on_sync else 0
                mapped = [e.index for e in layout.entries]
                slots = tuple(mapped.index(x) if x in mapped else -1 for x in _FEEDBACK)
                self._tpdo[layout.cob_id(node)] = (bit, layout.name, layout.struct, slots)
                self._routes[layout.cob_id(node)] = (self._on_tpdo, i)
            self._routes[EMCY_BASE + node] = (self._on_emcy, i)
            self._routes[HEARTBEAT_BASE + node] = (self._on_heartbeat, i)
        # feedback: SYNCs sent; per drive the TPDO bits seen since the latest SYNC (-1:
        # sample complete) and the SYNC count they belong to
        self._epoch = 0
        # clock() when the latest SYNC went out: a TPDO that arrived before it answers an
        # earlier SYNC (an arrival is never earlier than the frame's: its own stamp where
        # a thread reads the bus, else when the loop was handed it, FrameIO.arrival)
        self._sync_at = -math.inf
        self._cycle_syncs = (-math.inf, -math.inf)  # the latest two SYNCs cycle_start sent
        self._full = (1 << len(synced)) - 1
        self._got = [0] * self.n
        self._got_epoch = [-1] * self.n
        self.position: list[int | None] = [None] * self.n  # last position actual (increments)
        self._velocity = [0] * self.n
        self._differentiate = not self.plan.velocity
        self._sample: list[tuple[float, float]] = [(math.nan, 0.0)] * self.n  # length, SYNC
        self._statusword = [0] * self.n
        self.mode_display = [0] * self.n
        self._standing: list[tuple[int, bytes]] = []  # frames keepalive() repeats
        # after a brake: each drive asked by SDO whether it holds, in any NMT state
        self.hold_check = HoldCheck(
            self.nodes, self.status, config.has_holding_brake, timeout=self.hold_check_timeout
        )
        for i, node in enumerate(self.nodes):
            self._routes[SDO_RESPONSE_BASE + node] = (self._on_sdo_answer, i)
        self._feeding = False  # start() repeats them with each SDO request
        self._in_sequence = False  # a sequence's SDO exchanges run (no hold check then)

    # -- cycle ----------------------------------------------------------------------------

    def cycle_start(self) -> list[can.Message]:
        """SYNC, and the host heartbeat when one is due (the drives consume it: 0x1016)."""
        frames = self._sync()
        self._cycle_syncs = (self._cycle_syncs[1], self._sync_at)
        return frames

    def _sync(self) -> list[can.Message]:
        self._epoch += 1
        now = self.clock()  # the moment the drives latch their TPDOs
        self._sync_at = now
        return [encode_sync(), *self._heartbeat_due()]

    def _cycle_runs(self) -> bool:
        """The daemon's cycle sends SYNCs: its latest came within two of its periods."""
        before, latest = self._cycle_syncs
        period = latest - before  # inf after one SYNC: no cycle known yet
        return period < math.inf and self.clock() - latest < 2.0 * period

    def _heartbeat_due(self) -> list[can.Message]:
        """The host heartbeat if host_heartbeat_period has passed since the last one, by
        `clock` (the daemon's monotonic time: paced by the core's cycle timer, and by the
        SDO exchanges of a start-up or reset, never by the companion process)."""
        now = self.clock()
        if now < self._next_heartbeat:
            return []
        self._next_heartbeat = now + self._heartbeat_period
        self._heartbeats_sent.append(now)
        return [self._heartbeat]

    def _host_silence(self, now: float) -> str:
        """What this host's own record says of a drive's "heartbeat lost" (EMCY 0x8130)
        arriving at `now`: the longest it sent no heartbeat over the two consumer times
        before, and so whether the host was held up (as long as the consumer time: the
        drive was right to stop) or sent them and the drive did not hear them (the bus,
        its wiring, or the drive)."""
        consumer = self._consumer_time
        sent, since = [*self._heartbeats_sent, now], now - 2 * consumer
        gap = max((b - a for a, b in pairwise(sent) if b >= since), default=0.0)
        said = f"the drives' consumer time {consumer * 1e3:g} ms"
        if gap >= consumer:
            return f"this host sent no heartbeat for {gap * 1e3:.1f} ms ({said}): it was held up"
        return (
            f"this host's heartbeats went out at most {gap * 1e3:.1f} ms apart ({said}): "
            "the drive did not hear them (the bus, its wiring, or the drive)"
        )

    def commands(self, forces: Sequence[float]) -> list[can.Message]:
        if len(forces) != self.n:
            raise FrameError(f"{len(forces)} forces for {self.n} CiA 402 drives")
        torques = []
        permille, limits = self._permille, self.max_torque
        for i in range(self.n):
            force = forces[i]
            if not _isfinite(force):
                raise FrameError(
                    f"force {force} for cable {i} (node {self.nodes[i]}) is not finite"
                )
            torque = round(force * permille[i])
            limit = limits[i]
            if torque > limit:
                torque = limit
                self.torque_limited[i] += 1
            elif torque < -limit:
                torque = -limit
                self.torque_limited[i] += 1
            torques.append(torque)
        frames = self._torque_frames(torques)
        if self._control:  # the torque goes first: mode 10 then starts from it
            for i in range(self.n):
                if not self._in_torque[i]:
                    self._in_torque[i] = True
                    frames.append(data_frame(self._cw_ids[i], self._cw_pack(_ENABLE, 0, MODE_CST)))
        self._standing = []
        if self.hold_check.armed:
            self.hold_check.disarm()
        return frames

    def brake(self, lengths: Sequence[float], mode: BrakeMode) -> list[can.Message]:
        """Freeze every cable (module docstring).  Never raises: a drive without a usable
        length (none trusted yet, so never enabled by this host) gets the power-stage-off
        frame, never a hold at a position some frame reported."""
        if mode is BrakeMode.HOLDING_BRAKE and not self.config.has_holding_brake:
            mode = BrakeMode.POSITION_HOLD
        standing = []
        for i in range(self.n):
            target = self._hold_target(i, lengths[i] if i < len(lengths) else math.nan)
            if mode is BrakeMode.POSITION_HOLD and target is not None:
                standing.append((self._rpdo2[i], self._hold_pack(_ENABLE, target, MODE_CSP)))
            else:
                off = self._cw_pack(DISABLE_OPERATION.value, 0, MODE_CST)
                standing.append((self._cw_ids[i], off))
        self._standing = standing
        self._in_torque = [False] * self.n
        self.hold_check.arm(mode)  # asked from the next keepalive, the hold acted on by then
        return self._standing_frames()

    def disable(self) -> list[can.Message]:
        """Disable voltage with the release-hold bit: every power stage off, also a
        drive holding by its own fault reaction; holding brakes engage where fitted."""
        word = Command.DISABLE_VOLTAGE.value | CONTROL_RELEASE_HOLD
        self._standing = [(can_id, self._cw_pack(word, 0, MODE_CST)) for can_id in self._cw_ids]
        self._in_torque = [False] * self.n
        self.hold_check.disarm()  # no hold is asked for: nothing to confirm
        return self._standing_frames()

    def keepalive(self) -> list[can.Message]:
        """The latest brake/disable/enable frames again (none after torque commands: a
        torque command is never repeated), and after a brake the requests that confirm
        it reached every drive (drivers.cia402.hold_check)."""
        frames = self._standing_frames()
        if self.hold_check.armed and not self._in_sequence:
            frames += self.hold_check.frames(self.clock())
        return frames

    def _standing_frames(self) -> list[can.Message]:
        return [data_frame(can_id, data) for can_id, data in self._standing]

    def _hold_target(self, i: int, length: float) -> int | None:
        """Position (increments) holding cable i at `length`; None if it has none."""
        if _isfinite(length):
            position = self.scalings[i].position(length)
            if I32_MIN <= position <= I32_MAX:
                return round(position)
        return None

    # -- input ----------------------------------------------------------------------------

    def receive_ids(self) -> frozenset[int]:
        return frozenset(self._routes) | {SDO_RESPONSE_BASE + node for node in self.nodes}

    def receive(self, message: can.Message, now: float) -> int | None:
        if message.is_extended_id or message.is_error_frame:
            return None
        route = self._routes.get(message.arbitration_id)
        if route is None:
            return None
        if message.is_remote_frame:
            self.counters.reject("remote frame")
            return None
        handler, i = route
        try:
            return handler(i, message.arbitration_id, message.data, now)
        except Cia402FrameError as exc:
            self.counters.reject(exc.reason)
            return None

    def _on_tpdo(self, i: int, can_id: int, data: bytearray, now: float) -> int | None:
        """One TPDO of drive i, received at `now`; the last of its TPDOs since the latest
        SYNC completes the sample (positions latched at that SYNC); any TPDO after that is
        stale, and so is one received before that SYNC went out (an answer to an earlier
        one, read late: taken as this SYNC's it would put the length a period back and
        its rate over the wrong interval)."""
        bit, name, layout, slots = self._tpdo[can_id]
        if len(data) != layout.size:
            raise Cia402FrameError(
                can_id, f"{name} length", f"{len(data)} bytes, {name} has {layout.size}"
            )
        values = layout.unpack(data)
        status_at, position_at, velocity_at, mode_at = slots
        if status_at >= 0:
            word = values[status_at]
            state402 = decode_statusword(word)
            if state402 is None:
                raise Cia402FrameError(
                    can_id, "statusword pattern", f"0x{word:04X} is no 402 state"
                )
        if bit and now < self._sync_at:
            self.counters.reject("TPDO received before the latest SYNC")
            return None
        if bit:
            if self._got_epoch[i] != self._epoch:
                self._got_epoch[i], self._got[i] = self._epoch, 0
            got = self._got[i]
            if (got < 0 or got & bit) and position_at >= 0:
                self._second_answer(i, values[position_at])
            if got < 0:
                self.counters.reject("TPDO after the sample was complete")
                return None
        self.counters.accepted += 1
        if mode_at >= 0:
            self.mode_display[i] = values[mode_at]
        if status_at >= 0:
            self._statusword[i] = word
            self._update_state(i, word, self.mode_display[i], state402)
        if position_at >= 0:
            self.position[i] = values[position_at]
        if velocity_at >= 0:
            self._velocity[i] = values[velocity_at]
        if not bit:  # event-driven: no part of the cycle's sample
            return None
        got = self._got[i] | bit
        if got != self._full:
            self._got[i] = got
            return None
        self._got[i] = -1
        if self.position[i] is None:
            return None
        scaling, feedback = self.scalings[i], self.feedback[i]
        length = feedback.length = scaling.length(self.position[i])
        if self._differentiate:  # over the time between the SYNCs that latched them
            last, at = self._sample[i]
            sync = self._sync_at
            feedback.rate = (length - last) / (sync - at) if sync > at and _isfinite(last) else 0.0
            self._sample[i] = (length, sync)
        else:
            feedback.rate = scaling.rate(self._velocity[i], length)
        if scaling.spool is not None:  # the drum's radius follows the length
            rated = self.config.rated_torque or 1.0
            self._permille[i] = scaling.motor_torque(1.0, length) / rated * 1000.0
        feedback.stamp = now
        feedback.latched = self._sync_at
        feedback.count += 1
        return i

    def _second_answer(self, i: int, position: int) -> None:
        """Drive i answered the latest SYNC again with `position` (module docstring): its
        length is recorded as Feedback.second beside the first answer's, when that pair
        disagrees more than the one recorded."""
        first = self.position[i]
        if first is None:
            return
        scaling, feedback = self.scalings[i], self.feedback[i]
        length, other = scaling.length(position), scaling.length(first)
        if not abs(feedback.second - feedback.first) >= abs(length - other):  # or none yet
            feedback.first, feedback.second = other, length

    def _update_state(self, i: int, statusword: int, mode: int, state402: State | None) -> None:
        """Drive i's status from its statusword (decoded: `state402`) and mode display."""
        status = self.status[i]
        state = drive_state(state402, mode, bool(statusword & STATUS_HOLD))
        if state402 is State.OPERATION_ENABLED and mode not in MODES:
            # the drive runs a mode the host never commands: it does not do what it is told
            status.state = DriveState.FAULT
            if status.fault is None:
                status.fault = (
                    f"node {self.nodes[i]}: mode of operation display {mode} while operation "
                    "is enabled (the host commands 8 or 10)"
                )
            return
        if status.fault_code or self._lost[i]:
            # An EMCY is a fault (DESIGN §9) even while the statusword looks healthy: it
            # stays until an error-reset EMCY (code 0) or reset_faults.  So does a restart
            # (a boot-up heartbeat, even a forged one), until start() runs again.
            state = DriveState.FAULT
        status.state = state
        if state is DriveState.FAULT and status.fault is None:
            status.fault = "statusword reports FAULT (no EMCY received)"

    def _on_sdo_answer(self, i: int, can_id: int, data: bytearray, now: float) -> None:
        """An SDO answer outside a sequence: the brake's confirmation may wait for it
        (a sequence's own answers reach its Link; the check is disarmed meanwhile)."""
        if self.hold_check.armed and not self._in_sequence:
            self.hold_check.receive(i, can_id, data)

    def _on_emcy(self, i: int, can_id: int, data: bytearray, now: float) -> None:
        code, register, _ = decode_emcy(can_id, data)
        self.counters.accepted += 1
        status = self.status[i]
        if code == 0:  # error reset: the state follows from the next statusword
            status.fault, status.fault_code = None, 0
        else:
            status.state = DriveState.FAULT
            status.fault = f"{emcy_text(code)} (error register 0x{register:02X})"
            if code == HEARTBEAT_LOST and self._heartbeats_sent:
                status.fault += f"; {self._host_silence(now)}"
            status.fault_code = code

    def _on_heartbeat(self, i: int, can_id: int, data: bytearray, now: float) -> None:
        state = decode_heartbeat(can_id, data)
        self.counters.accepted += 1
        self.status[i].heartbeat_stamp = now
        self.nmt_state[i] = state
        if self._started[i] and state is not NmtState.OPERATIONAL:
            self._started[i] = False
            self._lost[i] = True
            status = self.status[i]
            status.state, status.fault_code = DriveState.FAULT, 0
            status.restarts += state is NmtState.BOOT_UP
            status.fault = (
                f"node {self.nodes[i]}: the drive restarted (boot-up heartbeat while "
                "operational): its configuration and position are lost; it needs start() again"
                if state is NmtState.BOOT_UP
                else f"node {self.nodes[i]}: NMT state {state.name.lower()}: PDOs stopped; "
                "it needs start() again"
            )

    # -- sequences ------------------------------------------------------------------------

    @contextlib.contextmanager
    def _sequence(self) -> Iterator[None]:
        """A sequence's SDO exchanges run: the brake's hold check waits (a request of
        its in flight is forgotten; the drives it had not confirmed are asked afresh)."""
        self.hold_check.pause()
        self._in_sequence = True
        try:
            yield
        finally:
            self._in_sequence = False

    async def start(self, link: Link, now: Callable[[], float]) -> None:
        self.clock = now  # the link's time (simulated time in lock-step runs)
        found: list[State] = []
        self._standing, self._feeding = [], True
        try:
            with self._sequence():
                await self._start(link, now, found)
        finally:
            self._feeding = False

    async def _start(self, link: Link, now: Callable[[], float], found: list[State]) -> None:
        config = self.config
        if self._shared:  # a shared torque frame must carry each drive's torque at once
            await self._read_held_torques(link)
        words = []
        for i in range(self.n):  # first what every drive does: take over the enabled ones
            self._started[i] = self._lost[i] = False
            words.append(await self._read(link, i, STATUSWORD))
            found.append(self._state_of(i, words[i]))
            if found[i] is State.OPERATION_ENABLED:
                await self._take_over(link, i)
        for i, node in enumerate(self.nodes):
            statusword, state = words[i], found[i]
            device_type = await self._read(link, i, DEVICE_TYPE)
            if device_type & 0xFFFF != DEVICE_PROFILE_402:
                raise DriverError(
                    f"node {node}: device type 0x{device_type:08X} is no CiA 402 drive"
                )
            if state not in _HOLDING and not statusword & STATUS_HOLD:
                # PDOs are configured in pre-operational; never on a drive holding a load
                link.send(encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, node))
            await self._configure_pdos(link, i)
            rated = await self._read(link, i, RATED_TORQUE) / 1000.0
            assert config.rated_torque is not None
            if abs(rated - config.rated_torque) > 0.005 * config.rated_torque:
                raise DriverError(
                    f"node {node}: motor rated torque 0x6076 is {rated} N·m, "
                    f"config rated_torque is {config.rated_torque} N·m"
                )
            for step in self.plan.writes:
                await self._write(link, i, step.index, step.subindex, step.value, step)
            # after the writes: a profile's sdo_writes may set it
            self.max_torque[i] = await self._read(link, i, MAX_TORQUE)
        for node in self.nodes:
            link.send(encode_nmt(NmtCommand.START, node))
        await self._await_heartbeats(link, now)
        for i in range(self.n):
            state = await self._read_state(link, i)
            if state is State.NOT_READY_TO_SWITCH_ON:
                state = await self._await_state(link, i, State.SWITCH_ON_DISABLED, "boot")
            if state is State.SWITCH_ON_DISABLED:
                state = await self._command(link, i, Command.SHUTDOWN, State.READY_TO_SWITCH_ON)
            if state is State.READY_TO_SWITCH_ON:
                await self._command(link, i, Command.SWITCH_ON, State.SWITCHED_ON)
            await self._refresh_status(link, i)
            self._started[i] = True
        taken = {
            can_id
            for i, s in enumerate(found)
            if s is State.OPERATION_ENABLED
            for can_id in (self._rpdo1[i], self._rpdo2[i])
        }
        self._standing = [(can_id, data) for can_id, data in self._standing if can_id in taken]

    async def _take_over(self, link: Link, i: int) -> None:
        """Drive i is OPERATION ENABLED (another master, or this host before a restart):
        keep it doing what it does (module docstring), starting now."""
        mode = await self._read(link, i, MODE_DISPLAY)
        position = await self._read(link, i, POSITION_ACTUAL)
        self.position[i] = position
        self._release_standing(i)
        if mode == MODE_CST:
            self._in_torque[i] = True
            if self._shared:  # every drive's torque, read before any went out
                frame = (self._rpdo1[i], bytes(self._torque_frames(self._held)[0].data))
            else:
                torque = await self._read(link, i, TARGET_TORQUE)
                frame = (self._rpdo1[i], self._torque_pack(_ENABLE, torque, MODE_CST))
            self._standing = [f for f in self._standing if f[0] != frame[0]]
        else:
            frame = (self._rpdo2[i], self._hold_pack(_ENABLE, position, MODE_CSP))
        self._standing.append(frame)
        link.send(data_frame(*frame))

    async def _read_held_torques(self, link: Link) -> None:
        """The target torque of every drive found applying one (OPERATION ENABLED in mode
        10), before the shared torque frame that carries them all goes out."""
        self._held = [0] * self.n
        for i in range(self.n):
            if self._state_of(i, await self._read(link, i, STATUSWORD)) is not (
                State.OPERATION_ENABLED
            ):
                continue
            if await self._read(link, i, MODE_DISPLAY) == MODE_CST:
                self._held[i] = await self._read(link, i, TARGET_TORQUE)

    async def _configure_pdos(self, link: Link, i: int) -> None:
        """The profile's PDO mapping in drive i (CiA 301 procedure) where it differs, read
        back; every other PDO of the EDS switched off."""
        node = self.nodes[i]
        checks = self._pdo_checks(node, i)
        values = [await self._read(link, i, index, sub) for index, sub, _, _ in checks]
        if any(v != expected for v, (_, _, expected, _) in zip(values, checks, strict=True)):
            for layout in self.plan.layouts:
                for index, sub, value in layout.mapping_procedure(node, i):
                    await self._write(link, i, index, sub, value)
            for index, sub, expected, what in checks:
                value = await self._read(link, i, index, sub)
                if value != expected:
                    raise DriverError(
                        f"node {node}: {what} reads 0x{value:X} after configuration, the "
                        f"profile maps 0x{expected:X} ({self.eds.name})"
                    )
        for comm in self.plan.unused:
            cob = await self._read(link, i, comm, 1)
            if not cob & PDO_INVALID:
                await self._write(link, i, comm, 1, cob | PDO_INVALID)

    async def enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
        with self._sequence():
            await self._enable(link, lengths, forces)
        self.hold_check.disarm()  # every drive holds by the enable's own confirmation

    async def _enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
        """Every drive to OPERATION ENABLED in position hold (mode 8) at `lengths`, so the
        cables stay put until the first torque command switches a drive to mode 10.
        `forces` are not needed: the hold carries the load until that command."""
        if len(lengths) != self.n:
            raise DriverError(f"enable needs {self.n} cable lengths, got {len(lengths)}")
        targets = []
        for i, length in enumerate(lengths):
            position = self.scalings[i].position(length) if _isfinite(length) else math.nan
            if not I32_MIN <= position <= I32_MAX:
                raise DriverError(
                    f"enable: cable {i} length {length} m is not a position node "
                    f"{self.nodes[i]} can hold"
                )
            targets.append(round(position))
        for i, node in enumerate(self.nodes):
            self._require_started(i)
            state = await self._read_state(link, i)
            if state in _FAULTED:
                raise DriverError(
                    f"node {node} is in FAULT ({self.status[i].fault}); reset faults first"
                )
            if state is State.SWITCH_ON_DISABLED:
                await self._command(link, i, Command.SHUTDOWN, State.READY_TO_SWITCH_ON)
        self._standing = [
            (self._rpdo2[i], self._hold_pack(_ENABLE, target, MODE_CSP))
            for i, target in enumerate(targets)
        ]
        self._in_torque = [False] * self.n
        round_timeout = min(0.02, self.config.watchdog_timeout / 2, self._heartbeat_period)
        pending = set(range(self.n))
        seen: dict[int, tuple[State | None, int]] = {}
        for _ in range(max(1, math.ceil(self.enable_timeout / round_timeout))):
            frames = self.keepalive()
            # a SYNC to answer, unless the daemon's cycle sends them: with a second source
            # between its SYNCs, answers to each were read after the other's went out
            # (taken for its answers, or dropped as a SYNC's before: in the UML guest,
            # every drive went stale and the enable braked)
            if not self._cycle_runs():
                frames += self._sync()
            for frame in frames:
                link.send(frame)
            with contextlib.suppress(DriverError):  # not yet: send the next round
                await link.expect(
                    self._enabled_collector(pending, seen),
                    round_timeout,
                    f"OPERATION ENABLED in position hold from nodes {self._names(pending)}",
                )
            faulted = [i for i, (state, _) in seen.items() if state in _FAULTED]
            if faulted:
                raise DriverError(f"enable: node(s) {self._names(faulted)} went to FAULT")
            if not pending:
                return
        last = ", ".join(
            f"node {self.nodes[i]}: {seen[i][0].name if i in seen and seen[i][0] else 'no TPDO1'}"
            for i in sorted(pending)
        )
        raise DriverError(
            f"enable: node(s) {self._names(pending)} did not reach OPERATION ENABLED in "
            f"position hold within {self.enable_timeout} s ({last})"
        )

    @property
    def measures_force(self) -> bool:
        """The EDS has torque actual 0x6077."""
        return TORQUE_ACTUAL in self.od

    async def measured_forces(self, link: Link) -> list[float]:
        """Torque actual 0x6077 of every drive by SDO (per mille of rated torque), as
        forces along +l at each cable's latest length."""
        if not self.measures_force:
            return await super().measured_forces(link)
        rated = self.config.rated_torque
        assert rated is not None  # DrivesConfig requires it for cia402
        forces = []
        with self._sequence():  # one SDO request per drive at a time: the hold check waits
            for i, scaling in enumerate(self.scalings):
                permille = await self._read(link, i, TORQUE_ACTUAL)
                forces.append(scaling.force(permille * rated / 1000.0, self.feedback[i].length))
        return forces

    async def reset_faults(self, link: Link) -> None:
        with self._sequence():
            await self._reset_faults(link)
        self.hold_check.disarm()  # no longer braked

    async def _reset_faults(self, link: Link) -> None:
        for i, node in enumerate(self.nodes):
            self._require_started(i)
            state = await self._read_state(link, i)
            if state in _FAULTED or state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON):
                # keepalive() must not send this node "enable operation" while the reset
                # steps it through the state machine; it holds by its own latched reaction
                self._release_standing(i)
            if state in _FAULTED:
                # bit 7 low first, so the reset is a rising edge whatever was sent before
                await self._write(link, i, CONTROLWORD, 0, Command.DISABLE_VOLTAGE.value)
                await self._write(link, i, CONTROLWORD, 0, Command.FAULT_RESET.value)
                for _ in range(self.state_polls):
                    state = await self._read_state(link, i)
                    if state not in _FAULTED:
                        break
                else:
                    code = await self._read(link, i, ERROR_CODE)
                    raise DriverError(
                        f"node {node}: still in FAULT after a fault reset, its cause persists "
                        f"({emcy_text(code)})"
                    )
            if state is State.SWITCH_ON_DISABLED:
                state = await self._command(link, i, Command.SHUTDOWN, State.READY_TO_SWITCH_ON)
            if state is State.READY_TO_SWITCH_ON:
                await self._command(link, i, Command.SWITCH_ON, State.SWITCHED_ON)
            await self._refresh_status(link, i)

    # -- sequence helpers -----------------------------------------------------------------

    def _release_standing(self, i: int) -> None:
        """Stop repeating brake/enable frames to drive i (keepalive; a shared torque
        frame stays: it is the other drives' too)."""
        mine = {self._rpdo2[i], self._cw_ids[i]} | (set() if self._shared else {self._rpdo1[i]})
        self._standing = [(can_id, data) for can_id, data in self._standing if can_id not in mine]

    def _names(self, indices: Iterable[int]) -> str:
        return ", ".join(str(self.nodes[i]) for i in sorted(indices))

    def _require_started(self, i: int) -> None:
        if not self._started[i]:
            raise DriverError(
                f"node {self.nodes[i]} is not started ({self.status[i].fault or 'start() not run'})"
            )

    def _pdo_checks(self, node: int, slot: int) -> list[tuple[int, int, int, str]]:
        """(index, sub, value the profile needs, what) for the PDO configuration of the
        drive that fills `slot` of the shared PDOs."""
        checks = []
        for layout in self.plan.layouts:
            comm, mapping, entries = layout.comm_index, layout.map_index, layout.mapped(slot)
            checks.append((comm, 1, layout.cob_id(node), f"{layout.name} COB-ID 0x{comm:04X}:01"))
            checks.append((comm, 2, layout.transmission_type, f"{layout.name} transmission type"))
            if layout.inhibit:
                checks.append((comm, 3, layout.inhibit, f"{layout.name} inhibit time"))
            checks.append((mapping, 0, len(entries), f"{layout.name} mapped object count"))
            checks.extend(
                (
                    mapping,
                    k + 1,
                    entry.mapping,
                    f"{layout.name} mapping 0x{mapping:04X}:{k + 1:02X}",
                )
                for k, entry in enumerate(entries)
            )
        return checks

    def _sdo_reply(
        self, node: int, index: int | None, sub: int = 0
    ) -> Callable[[can.Message], bool]:
        """Match the server's answer: to an initiate (`index` given, scs 2, 3 or 4 with
        that object) or to a segment (`index` None: scs 0, 1 or 4)."""
        can_id = SDO_RESPONSE_BASE + node
        head = None if index is None else bytes((index & 0xFF, index >> 8, sub))

        def match(message: can.Message) -> bool:
            data = message.data
            if message.arbitration_id != can_id or message.is_extended_id or len(data) != 8:
                return False
            scs = data[0] >> 5
            if head is None:
                return scs in (0, 1, 4)
            return scs in (2, 3, 4) and data[1:4] == head

        return match

    async def _answer(
        self, link: Link, i: int, request: can.Message, index: int | None, sub: int, what: str
    ):
        if self._feeding:  # drives taken over keep getting their frames through start()
            for frame in self.keepalive():
                link.send(frame)
        for frame in self._heartbeat_due():  # the drives' consumers stay fed too
            link.send(frame)
        link.send(request)
        reply = await link.expect(
            self._sdo_reply(self.nodes[i], index, sub), self.sdo_timeout, what
        )
        sdo = decode_sdo_response(reply.arbitration_id, reply.data)
        if sdo.kind is SdoKind.ABORT:
            raise DriverError(f"{what} aborted: {abort_text(sdo.abort_code)}")
        return sdo

    async def _upload(self, link: Link, i: int, index: int, sub: int, what: str) -> bytes:
        """Read an object, expedited or segmented."""
        node = self.nodes[i]
        sdo = await self._answer(
            link, i, encode_sdo_upload_request(node, index, sub), index, sub, what
        )
        if sdo.kind is not SdoKind.UPLOAD:
            raise DriverError(f"{what}: the drive answered {sdo.kind.value}, not an upload")
        if not sdo.segmented:
            return sdo.data
        data, toggle = b"", 0
        for _ in range(0x10000):
            ask = encode_sdo_segment_ask(node, toggle, server=False)
            segment = await self._answer(link, i, ask, None, 0, what)
            if segment.kind is not SdoKind.SEGMENT or segment.toggle != toggle:
                raise DriverError(f"{what}: segment out of sequence (toggle {toggle} expected)")
            data += segment.data
            if segment.last:
                break
            toggle ^= 1
        if sdo.size is not None and sdo.size >= 0 and len(data) != sdo.size:
            raise DriverError(f"{what}: {len(data)} bytes, the drive announced {sdo.size}")
        return data

    async def _download(
        self, link: Link, i: int, index: int, sub: int, data: bytes, what: str
    ) -> None:
        """Write an object: expedited up to 4 bytes, segmented above."""
        node = self.nodes[i]
        if len(data) <= 4:
            request = encode_sdo_download_request(node, index, sub, data)
            await self._answer(link, i, request, index, sub, what)
            return
        await self._answer(
            link, i, encode_sdo_download_initiate(node, index, sub, len(data)), index, sub, what
        )
        toggle = 0
        for start in range(0, len(data), 7):
            chunk = data[start : start + 7]
            last = start + 7 >= len(data)
            reply = await self._answer(
                link, i, encode_sdo_segment(node, toggle, chunk, last, server=False), None, 0, what
            )
            if reply.kind is not SdoKind.SEGMENT_ASK or reply.toggle != toggle:
                raise DriverError(f"{what}: segment confirmation out of sequence")
            toggle ^= 1

    async def _read(self, link: Link, i: int, index: int, sub: int = 0) -> int:
        node, var = self.nodes[i], od_variable(self.od, index, sub)
        what = f"node {node}: SDO read 0x{index:04X}:{sub:02X} ({var.name})"
        data = await self._upload(link, i, index, sub, what)
        if len(data) != len(var) // 8:
            raise DriverError(f"{what}: {len(data)} bytes, the object has {len(var) // 8}")
        return int(var.decode_raw(data))

    async def _write(
        self,
        link: Link,
        i: int,
        index: int,
        sub: int,
        value: int | bytes,
        step: SdoStep | None = None,
    ) -> None:
        node, var = self.nodes[i], od_variable(self.od, index, sub)
        detail = (
            step.what if step is not None else f"0x{index:04X}:{sub:02X} ({var.name}) = {value}"
        )
        what = f"node {node}: SDO write {detail}"
        data = value if isinstance(value, bytes) else var.encode_raw(value)
        if index == CONTROLWORD:  # the next torque command sends the control RPDO again
            self._in_torque[i] = False
        await self._download(link, i, index, sub, data, what)

    def _state_of(self, i: int, statusword: int) -> State:
        state = decode_statusword(statusword)
        if state is None:
            raise DriverError(
                f"node {self.nodes[i]}: statusword 0x{statusword:04X} is no CiA 402 state"
            )
        return state

    async def _read_state(self, link: Link, i: int) -> State:
        return self._state_of(i, await self._read(link, i, STATUSWORD))

    async def _await_state(self, link: Link, i: int, wanted: State, what: str) -> State:
        for _ in range(self.state_polls):
            state = await self._read_state(link, i)
            if state is wanted:
                return state
        raise DriverError(
            f"node {self.nodes[i]}: {what} did not reach {wanted.name} (it is {state.name})"
        )

    async def _command(self, link: Link, i: int, command: Command, wanted: State) -> State:
        await self._write(link, i, CONTROLWORD, 0, command.value)
        return await self._await_state(link, i, wanted, f"controlword {command.name}")

    async def _refresh_status(self, link: Link, i: int) -> None:
        """Status from a fresh statusword (and fault text from 0x603F in FAULT), via SDO."""
        status = self.status[i]
        status.fault, status.fault_code = None, 0
        statusword = await self._read(link, i, STATUSWORD)
        mode = self.mode_display[i] = await self._read(link, i, MODE_DISPLAY)
        self._update_state(i, statusword, mode, decode_statusword(statusword))
        if status.state is DriveState.FAULT:
            code = await self._read(link, i, ERROR_CODE)
            status.fault, status.fault_code = emcy_text(code), code

    async def _await_heartbeats(self, link: Link, now: Callable[[], float]) -> None:
        pending, started = set(range(self.n)), now()
        index = {HEARTBEAT_BASE + node: i for i, node in enumerate(self.nodes)}

        def match(message: can.Message) -> bool:
            i = index.get(message.arbitration_id)
            if i is not None and not message.is_extended_id and bytes(message.data) == b"\x05":
                self.status[i].heartbeat_stamp = now()
                pending.discard(i)
            return not pending

        timeout = self.config.heartbeat_timeout
        # keepalive and heartbeat between steps
        step = min(timeout, self.config.watchdog_timeout / 2, self._heartbeat_period)
        for _ in range(math.ceil(timeout / step)):
            # heartbeats that came between two steps (receive() saw them, no match did)
            pending -= {
                i
                for i in pending
                if self.nmt_state[i] is NmtState.OPERATIONAL
                and self.status[i].heartbeat_stamp >= started
            }
            if not pending:
                return
            if self._feeding:
                for frame in self.keepalive():
                    link.send(frame)
            for frame in self._heartbeat_due():
                link.send(frame)
            with contextlib.suppress(DriverError):
                await link.expect(match, step, "operational heartbeats from the CiA 402 nodes")
                return
        raise DriverError(
            f"no operational heartbeat from node(s) {self._names(pending)} within {timeout} s"
        )

    def _enabled_collector(
        self, pending: set[int], seen: dict[int, tuple[State | None, int]]
    ) -> Callable[[can.Message], bool]:
        """Match that records the states the TPDOs report (receive() decoded them) and is
        true once every pending drive reports OPERATION ENABLED in mode 8."""

        def match(message: can.Message) -> bool:
            route = self._routes.get(message.arbitration_id)
            if route is not None and route[0] == self._on_tpdo and not message.is_extended_id:
                i = route[1]
                seen[i] = (decode_statusword(self._statusword[i]), self.mode_display[i])
                if seen[i] == (State.OPERATION_ENABLED, MODE_CSP):
                    pending.discard(i)
            return not pending

        return match
