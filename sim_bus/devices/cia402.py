"""Device side of one CiA 402 drive in cyclic synchronous torque mode, for the simulator.

A strict drive, as bought: the object dictionary comes from config/can/cia402_cst.eds
(parsed by canopen; only standard objects), every object starts at its EDS value, and
the SDO server (expedited and segmented upload/download) reads and writes it with the
EDS's types, access rights and limits, answering unknown objects, read-only writes,
wrong sizes and out-of-range values with the CiA 301 abort codes (an expedited download
that does not indicate its size, e=1 s=0, carries the object's own size in its 4
bytes).  Rated torque 0x6076 is preset from the `drives:` config (the drive's stored
parameter); everything else keeps its EDS default until the host writes it: the CiA 402
default mapping (RPDO1 = controlword, TPDO1 = statusword, the other PDOs invalid),
heartbeat 0x1017 and consumer heartbeat 0x1016 off, no RPDO deadline, abort connection
option 0x6007 = 1 (fault), quick stop option 0x605A = 2 (ramp, then power stage off).

PDOs follow the mapping in the object dictionary: the master changes it by the CiA 301
procedure (COB-ID bit 31 set, sub0 = 0, entries, sub0, valid again); a mapping written
otherwise, or naming an object that cannot be mapped, is refused with the abort code.
An RPDO may map dummy entries (0x0002-0x0007) where the EDS's [DummyUsage] allows them:
their bytes are skipped, so drives sharing one RPDO COB-ID each take their own bytes.
RPDO fields are written into the dictionary (a mode of operation 0 means "no change"):
on reception for transmission type 254/255, at the next SYNC for type 0..240 (CiA 301
synchronous RPDO: the latest frame before that SYNC; dropped on leaving OPERATIONAL).
TPDOs (CiA 301 transmission types): type 1..240 go out on every n-th SYNC; type 0 on the
first SYNC after their data changed; type 254/255 when their data changes and when their
event timer 0x18xx:05 runs out (restarted by each transmission), at most once per
inhibit time 0x18xx:03; types 0, 254 and 255 also once on entering OPERATIONAL (on the
first SYNC for type 0).

NMT: boot-up message at the first tick (then PRE-OPERATIONAL), start / stop / enter
pre-operational / reset node / reset communication; SDO in pre-operational and
operational, PDOs (and SYNC -> TPDO1 + TPDO2 from `measure`) only in operational.

402 state machine (drivers.cia402.statemachine) driven by the controlword from RPDO1,
RPDO2 or SDO; operation enabled gives Actuation.TORQUE (mode 10, target torque per mille
of rated torque, clamped to +-0x6072) or Actuation.POSITION (mode 8, target position;
switching to mode 8 without a target, by RPDO1 or SDO, holds the actual position).

Reactions (DESIGN §9): a quick stop (controlword, or 0x6007 = 3 on a lost connection)
follows 0x605A: 5..8 hold the cable length and stay in QUICK STOP ACTIVE; 0..4 end in
SWITCH ON DISABLED with the power stage off (the holding brake engages where fitted,
else the cable is free).  0x6007 = 2 switches the power stage off the same way, 1 is a
fault.  The fault reaction (the drive's stored setting, `drives.brake`): a drive whose
power stage is on either holds the cable length it has at that moment (position hold)
or engages its holding brake and switches off; the reaction stays latched
(statusword bit 14) through FAULT, fault reset and SWITCH ON DISABLED — the drive never
moves by itself — until operation is enabled again or "disable voltage" comes with
controlword bit 15.  A drive whose power stage was off stays off (brake on where fitted).

RPDO deadlines (CiA 301 §7.5.2.35): each RPDO whose event timer 0x14xx:05 is non-zero has
its own, started by its first reception in OPERATIONAL and restarted by each one after, in
any 402 state; it expires 0x14xx:05 ms after that RPDO's latest reception (other RPDOs do
not feed it): brake reaction, FAULT, EMCY 0x8250 (a drive already in FAULT keeps its
fault and sends nothing), and it stays off until that RPDO comes again.  A deadline never
armed never fires; leaving OPERATIONAL, a reset, the RPDO switched off (COB-ID bit 31) or
its 0x14xx:05 set to 0 stop it.  Consumer heartbeat (0x1016 sub k = node << 16 | ms):
armed by the first heartbeat of that node, it expires that long after the latest: EMCY
0x8130 and the 0x6007 reaction.  `inject_fault`
does the same with any code; a fault reset (controlword bit 7 rising edge) clears the
fault unless its cause persists (`inject_fault(..., persistent=True)` until
`clear_fault_cause()`), and then sends the EMCY error reset (code 0).

Power-on hold (`power_on_hold`, default: drives without a holding brake): at power-on
(the first `measure`) and at every reset node the drive latches a position hold at the
measured length, as a suspended robot without brakes needs until the host starts; it
ends like any latched brake reaction.

Frames addressed to the drive that are malformed (wrong length, undefined NMT command or
mode, RTR) are counted in `counters.rejected` and ignored.
"""

from __future__ import annotations

import contextlib
import functools
import math
import struct
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import can
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from drivers.base import (
    Actuation,
    BrakeMode,
    FrameCounters,
    Scaling,
    VirtualDrive,
    data_frame,
)
from drivers.cia402.codec import (
    ABORT_CONNECTION_OPTION,
    ABORT_DEVICE_STATE,
    ABORT_LENGTH,
    ABORT_NO_DATA,
    ABORT_NO_SUBINDEX,
    ABORT_NOT_IN_OD,
    ABORT_NOT_MAPPABLE,
    ABORT_PDO_TOO_LONG,
    ABORT_READ_WRITE_ONLY,
    ABORT_TOGGLE,
    ABORT_UNSUPPORTED_COMMAND,
    ABORT_VALUE_HIGH,
    ABORT_VALUE_LOW,
    ABORT_VALUE_RANGE,
    ABORT_WRITE_READ_ONLY,
    COB_ID_SYNC,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    DUMMIES,
    EDS_PATH,
    ERROR_CODE,
    ERROR_REGISTER,
    HEARTBEAT_BASE,
    HEARTBEAT_LOST,
    I32_MAX,
    I32_MIN,
    MAX_TORQUE,
    MODE_DISPLAY,
    MODE_OF_OPERATION,
    NMT_ID,
    PDO_INVALID,
    POSITION_ACTUAL,
    PRODUCER_HEARTBEAT,
    QUICK_STOP_HOLD,
    QUICK_STOP_OPTION_CODE,
    RATED_TORQUE,
    RPDO_DEADLINE_SUB,
    SDO_REQUEST_BASE,
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
    decode_heartbeat,
    decode_nmt,
    decode_sdo_request,
    decode_sync,
    encode_emcy,
    encode_heartbeat,
    encode_sdo_abort,
    encode_sdo_download_response,
    encode_sdo_segment,
    encode_sdo_segment_ask,
    encode_sdo_upload_response,
    error_register,
    load_eds,
    od_value,
    pdo_layout,
)
from drivers.cia402.statemachine import (
    CONTROL_FAULT_RESET,
    CONTROL_RELEASE_HOLD,
    MODE_CSP,
    MODE_CST,
    MODE_NO_CHANGE,
    MODES,
    Command,
    State,
    decode_command,
    encode_statusword,
    next_state,
)
from drivers.config import DrivesConfig

RPDO_TIMEOUT = 0x8250
ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP = 1, 2, 3  # 0x6007 option codes
_FAULTED = (State.FAULT, State.FAULT_REACTION_ACTIVE)
_SDO_STATES = (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)


class Rpdo(NamedTuple):
    """A valid RPDO (CiA 301, 0x14xx / 0x16xx): where the EDS describes it, the objects
    it maps, its deadline 0x14xx:05 (s, 0: none), and whether it is synchronous
    (transmission type 0..240: its data take effect at the next SYNC; 254/255 at once)."""

    layout: PdoLayout
    keys: list[tuple[int, int]]
    deadline: float
    synchronous: bool


class Tpdo(NamedTuple):
    """A valid TPDO (CiA 301, 0x18xx / 0x1Axx): COB-ID, the struct of its frame, the
    objects it maps, transmission type `kind` (0: on the SYNC after its data changed;
    1..240: on every kind-th SYNC; 254/255: on change, and every `event_timer` where
    0x18xx:05 sets one), and `inhibit` (0x18xx:03), the least time between two frames of
    a type 254/255 TPDO.  Times in whole microseconds, the unit both objects count in
    (100 us, 1 ms): a period then ends on the tick it should, whatever float rounding."""

    cob: int
    layout: struct.Struct
    keys: list[tuple[int, int]]
    kind: int
    inhibit: int  # us
    event_timer: int  # us
    values: tuple[Callable[[], int], ...]  # each mapped object's value now, in order


def _i32(value: float) -> int:
    """An encoder reading saturated to the i32 range of 0x6064 / 0x606C."""
    if value >= I32_MAX:
        return I32_MAX
    if value <= I32_MIN:
        return I32_MIN
    return round(value)


class Cia402Drive(VirtualDrive):
    """One simulated CiA 402 drive at `node_id`, with the stored parameters of `config`.

    `counters` counts frames addressed to this drive (accepted / rejected by reason).
    `state` is its 402 state, `nmt_state` its NMT state (None before the boot-up),
    `hold` its latched brake reaction (None, POSITION_HOLD at `hold_length`, or
    HOLDING_BRAKE), `fault_code` / `fault_text` the active fault.
    """

    def __init__(
        self,
        node_id: int,
        scaling: Scaling,
        config: DrivesConfig,
        *,
        power_on_hold: bool | None = None,
        eds: str | Path = EDS_PATH,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node ids run 1..127, not {node_id}")
        if config.rated_torque is None:
            raise ValueError("a CiA 402 drive needs rated_torque (N·m)")
        super().__init__(node_id, scaling)
        self.od = load_eds(eds, node_id)
        self.rated_torque = config.rated_torque
        self.has_holding_brake = config.has_holding_brake
        self.power_on_hold = (
            not config.has_holding_brake if power_on_hold is None else power_on_hold
        )
        self.strings: dict[tuple[int, int], bytes] = {}  # string objects (0x1008)
        self._stored = {(RATED_TORQUE, 0): round(config.rated_torque * 1000)}
        # the fault reaction, a stored vendor setting of this drive (no standard object)
        self.brake_reaction = (
            BrakeMode.HOLDING_BRAKE
            if config.brake is BrakeMode.HOLDING_BRAKE and config.has_holding_brake
            else BrakeMode.POSITION_HOLD
        )
        self.counters = FrameCounters()
        self.nmt_state: NmtState | None = None
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.controlword = 0
        self.hold: BrakeMode | None = None
        self.hold_length = math.nan
        self.fault_code = 0
        self.fault_text: str | None = None
        self.fault_persistent = False
        self._powered = False
        self._expiry: dict[int, float] = {}  # RPDO COB-ID -> its deadline's expiry (armed)
        # synchronous RPDO COB-ID -> the fields of its latest frame, for the next SYNC
        self._pending: dict[int, dict[tuple[int, int], int]] = {}
        self._next_heartbeat = math.inf
        self._consumed: dict[int, float] = {}  # node -> its heartbeat's expiry
        # no deadline of _expiry or _consumed comes before this (a lower bound, exact
        # after each look): the watchdog, run on every frame, looks only once it is due
        self._soonest = math.inf
        self._transfer: tuple[str, tuple[int, int], bytes, int] | None = None  # segmented
        self._syncs = 0
        self._sent: dict[int, tuple[bytes, float]] = {}  # TPDO COB-ID -> data, time last sent
        self._live: dict[tuple[int, int], Callable[[], int]] = {
            (STATUSWORD, 0): lambda: encode_statusword(self.state, self.hold is not None),
            (CONTROLWORD, 0): lambda: self.controlword,
            (MODE_DISPLAY, 0): lambda: self.mode,
            (POSITION_ACTUAL, 0): self._reported_position,
            (VELOCITY_ACTUAL, 0): self._velocity,
            (TORQUE_ACTUAL, 0): self._torque_actual,
            (ERROR_CODE, 0): lambda: self.fault_code,
            (ERROR_REGISTER, 0): lambda: error_register(self.fault_code),
        }
        self._reset_values(communication_only=False)
        self._apply()

    # -- object dictionary ----------------------------------------------------------------

    def _reset_values(self, communication_only: bool) -> None:
        """Every object back to its EDS value (reset node), or only 0x1000-0x1FFF (reset
        communication); the stored parameters from the config win over the EDS."""
        values = (
            {}
            if not communication_only
            else {k: v for k, v in self.values.items() if k[0] >= 0x2000}
        )
        for index, entry in self.od.items():
            if communication_only and index >= 0x2000:
                continue
            members = entry.values() if isinstance(entry, ODRecord | ODArray) else (entry,)
            for var in members:
                value = od_value(var)
                if isinstance(value, int):
                    values[(var.index, var.subindex)] = value
                elif isinstance(value, str):
                    self.strings[(var.index, var.subindex)] = var.encode_raw(value)
        if not communication_only:
            values.update(self._stored)
        self.values: dict[tuple[int, int], int] = values
        self._settings()

    def _settings(self) -> None:
        """Cache the objects the drive consults on every frame or tick."""
        values = self.values
        self.mode = values[(MODE_OF_OPERATION, 0)]
        self.target_torque = values[(TARGET_TORQUE, 0)]
        self.target_position = values[(TARGET_POSITION, 0)]
        self.max_torque = values[(MAX_TORQUE, 0)]
        self.sync_id = values[(COB_ID_SYNC, 0)] & 0x7FF
        self.heartbeat_period = values[(PRODUCER_HEARTBEAT, 0)] / 1000.0
        consumers = {}
        for sub in range(1, values.get((CONSUMER_HEARTBEAT, 0), 0) + 1):
            entry = values.get((CONSUMER_HEARTBEAT, sub), 0)
            if entry >> 16 & 0x7F and entry & 0xFFFF:
                consumers[entry >> 16 & 0x7F] = (entry & 0xFFFF) / 1000.0
        self.consumers = consumers
        self._consumed = {n: t for n, t in self._consumed.items() if n in consumers}
        self._pdos()

    def _pdos(self) -> None:
        """Frame routes and TPDOs from the PDO configuration in the dictionary."""
        routes: dict[int, Callable[[can.Message, float], list[can.Message]]] = {
            NMT_ID: self._on_nmt,
            SDO_REQUEST_BASE + self.node_id: self._on_sdo,
        }
        self._rpdos: dict[int, Rpdo] = {}  # by COB-ID
        self.tpdos: list[Tpdo] = []
        # the PDOs' communication parameters in the dictionary (RPDOs' 0x1400-0x15FF,
        # then TPDOs' 0x1800-0x19FF): a scan of every index cost 130 us, and an SDO write
        # (several per drive while the daemon enables) redoes this
        comms = sorted(
            index
            for index, sub in self.values
            if sub == 1 and (0x1400 <= index < 0x1600 or 0x1800 <= index < 0x1A00)
        )
        for comm in comms:
            cob = self.values[(comm, 1)]
            if cob & PDO_INVALID:
                continue
            count = self.values.get((comm + 0x200, 0), 0)
            keys = [
                (entry >> 16, entry >> 8 & 0xFF)
                for entry in (self.values.get((comm + 0x200, k), 0) for k in range(1, count + 1))
            ]
            layout = pdo_layout(self.od, comm < 0x1800, (comm & 0x1FF) + 1, keys, 0)
            if comm < 0x1800:
                deadline = self.values.get((comm, RPDO_DEADLINE_SUB), 0) / 1000.0
                synchronous = self.values.get((comm, 2), 255) <= 240
                self._rpdos[cob & 0x7FF] = Rpdo(layout, keys, deadline, synchronous)
                routes[cob & 0x7FF] = self._on_rpdo
            else:
                self.tpdos.append(
                    Tpdo(
                        cob & 0x7FF,
                        layout.struct,
                        keys,
                        self.values.get((comm, 2), 0),
                        self.values.get((comm, 3), 0) * 100,
                        self.values.get((comm, 5), 0) * 1000,
                        tuple(self._reader(key) for key in keys),
                    )
                )
        self._event_driven = [tpdo for tpdo in self.tpdos if tpdo.kind in (254, 255)]
        self._routes = routes
        rpdos = self._rpdos
        self._expiry = {c: t for c, t in self._expiry.items() if c in rpdos and rpdos[c].deadline}
        self._pending = {
            c: fields for c, fields in self._pending.items() if c in rpdos and rpdos[c].synchronous
        }
        self.routes_changed()

    def hears(self, can_id: int) -> bool:
        return (
            can_id in self._routes
            or can_id == self.sync_id
            or can_id - HEARTBEAT_BASE in self.consumers
        )

    @property
    def rpdo_deadlines(self) -> dict[str, float]:
        """The deadline (s) of each valid RPDO that has one, by name (RPDO1, ...)."""
        return {rpdo.layout.name: rpdo.deadline for rpdo in self._rpdos.values() if rpdo.deadline}

    def _variable(self, index: int, subindex: int) -> ODVariable | int:
        """The OD variable, or the SDO abort code for a missing one."""
        entry = self.od.get(index)
        if entry is None:
            return ABORT_NOT_IN_OD
        if isinstance(entry, ODRecord | ODArray):
            return entry.get(subindex, ABORT_NO_SUBINDEX)
        return entry if subindex == 0 else ABORT_NO_SUBINDEX

    def _position(self) -> int:
        return _i32(self.scaling.position(self.length))

    def _reported_position(self) -> int:
        """Position actual as the drive reports it (TPDO1, SDO): with any glitch."""
        return _i32(self.scaling.position(self.length + self.glitch))

    def _velocity(self) -> int:
        return _i32(self.scaling.velocity(self.rate, self.length))

    # -- VirtualDrive ---------------------------------------------------------------------

    def measure(self, length: float, rate: float) -> None:
        super().measure(length, rate)
        if not self._powered:
            self._powered = True
            if self.power_on_hold:
                self.hold, self.hold_length = BrakeMode.POSITION_HOLD, length
                self._apply()

    def on_frame(self, message: can.Message, now: float) -> list[can.Message]:
        if self.nmt_state is None or message.is_extended_id or message.is_error_frame:
            return []  # not booted yet, or not CANopen
        out = self._watchdog(now)
        can_id = message.arbitration_id
        if can_id - HEARTBEAT_BASE in self.consumers and not message.is_remote_frame:
            with contextlib.suppress(Cia402FrameError):
                decode_heartbeat(can_id, message.data)
                expiry = now + self.consumers[can_id - HEARTBEAT_BASE]
                self._consumed[can_id - HEARTBEAT_BASE] = expiry
                self._soonest = min(self._soonest, expiry)
            return out
        handler = self._on_sync if can_id == self.sync_id else self._routes.get(can_id)
        if handler is None:
            return out
        if message.is_remote_frame:
            self.counters.reject("remote frame")
            return out
        try:
            out += handler(message, now)
        except Cia402FrameError as exc:
            self.counters.reject(exc.reason)
        return out + self._events(now)

    def on_tick(self, now: float) -> list[can.Message]:
        if self.nmt_state is None:
            return self._boot(now, communication_only=False)
        out = self._watchdog(now)
        if now >= self._next_heartbeat:
            out.append(encode_heartbeat(self.node_id, self.nmt_state))
            due = self._next_heartbeat + self.heartbeat_period
            self._next_heartbeat = due if due > now else now + self.heartbeat_period
        return out + self._events(now)

    def inject_fault(self, code: int, text: str, *, persistent: bool = False) -> list[can.Message]:
        """The drive detects fault `code` (an EMCY error code): brake reaction, FAULT,
        EMCY.  A persistent cause survives fault resets until `clear_fault_cause()`."""
        if not 0 < code <= 0xFFFF:
            raise ValueError(f"an EMCY error code is a non-zero u16, not {code}")
        return self._fault(code, text, persistent)

    def clear_fault_cause(self) -> None:
        """The cause of a persistent fault is gone; the next fault reset clears it."""
        self.fault_persistent = False

    # -- NMT, SYNC, heartbeat ---------------------------------------------------------------

    def _boot(self, now: float, communication_only: bool) -> list[can.Message]:
        """Boot-up after power-on or reset node (everything back to the EDS, power stage
        off) or after reset communication (0x1000-0x1FFF only; the 402 state stays)."""
        self._reset_values(communication_only)
        if not communication_only:
            self.state, self.hold, self.controlword = State.SWITCH_ON_DISABLED, None, 0
            if self.power_on_hold and self._powered:
                self.hold, self.hold_length = BrakeMode.POSITION_HOLD, self.length
            if not self.fault_persistent:
                self.fault_code, self.fault_text = 0, None
        self.nmt_state = NmtState.PRE_OPERATIONAL
        self._expiry, self._pending = {}, {}
        self._next_heartbeat = now + self.heartbeat_period if self.heartbeat_period else math.inf
        out = [encode_heartbeat(self.node_id, NmtState.BOOT_UP)]
        if self.fault_persistent and not communication_only:
            out += self._fault(self.fault_code, self.fault_text or "", True)
        self._apply()
        return out

    def _on_nmt(self, message: can.Message, now: float) -> list[can.Message]:
        command, node = decode_nmt(message.data)
        if node not in (0, self.node_id):
            return []
        self.counters.accepted += 1
        if command is NmtCommand.RESET_NODE:
            return self._boot(now, communication_only=False)
        if command is NmtCommand.RESET_COMMUNICATION:
            return self._boot(now, communication_only=True)
        self.nmt_state = {
            NmtCommand.START: NmtState.OPERATIONAL,
            NmtCommand.STOP: NmtState.STOPPED,
            NmtCommand.ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
        }[command]
        if self.nmt_state is not NmtState.OPERATIONAL:
            # no PDOs outside OPERATIONAL: the deadlines stop, received data is dropped
            self._expiry, self._pending = {}, {}
        self._sent = {}  # TPDOs of type 0, 254, 255 go out once on entering OPERATIONAL
        return []

    def _on_sync(self, message: can.Message, now: float) -> list[can.Message]:
        decode_sync(message.data)
        self.counters.accepted += 1
        if self.nmt_state is not NmtState.OPERATIONAL:
            return []
        self._syncs += 1
        out = []
        pending, self._pending = self._pending, {}
        for fields in pending.values():
            out += self._act(fields)
        for tpdo in self.tpdos:
            if tpdo.kind == 0:  # synchronous acyclic: the first SYNC after a change
                data = self._data(tpdo)
                if data != self._sent.get(tpdo.cob, (None,))[0]:
                    out.append(self._transmit(tpdo, data, now))
            elif tpdo.kind <= 240 and self._syncs % tpdo.kind == 0:
                out.append(self._transmit(tpdo, self._data(tpdo), now))
        return out

    def _events(self, now: float) -> list[can.Message]:
        """The event-driven TPDOs (types 254/255) that are due, where their inhibit time
        allows: their data changed since they were last sent, or their event timer ran
        out (CiA 301: it restarts with every transmission); each one once on entering
        OPERATIONAL."""
        if not self._event_driven or self.nmt_state is not NmtState.OPERATIONAL:
            return []
        out = []
        for tpdo in self._event_driven:
            data = self._data(tpdo)
            last = self._sent.get(tpdo.cob)
            if last is not None:
                elapsed = round((now - last[1]) * 1e6)
                timed_out = 0 < tpdo.event_timer <= elapsed
                if elapsed < tpdo.inhibit or (data == last[0] and not timed_out):
                    continue
            out.append(self._transmit(tpdo, data, now))
        return out

    def _data(self, tpdo: Tpdo) -> bytes:
        return tpdo.layout.pack(*[value() for value in tpdo.values])

    def _transmit(self, tpdo: Tpdo, data: bytes, now: float) -> can.Message:
        self._sent[tpdo.cob] = (data, now)
        return data_frame(tpdo.cob, data)

    def _reader(self, key: tuple[int, int]) -> Callable[[], int]:
        """What reads a mapped object's value when its TPDO goes out: its live source, or
        its entry in this dictionary (which SDO writes and RPDOs update in place)."""
        live = self._live.get(key)
        return live if live is not None else functools.partial(self.values.get, key, 0)

    # -- RPDOs ------------------------------------------------------------------------------

    def _on_rpdo(self, message: can.Message, now: float) -> list[can.Message]:
        """An RPDO, checked and feeding its deadline on reception; an event-driven one
        acts at once, a synchronous one at the next SYNC (CiA 301: the latest frame
        received before that SYNC is the one that acts)."""
        can_id = message.arbitration_id
        rpdo = self._rpdos[can_id]
        name, layout = rpdo.layout.name, rpdo.layout.struct
        if len(message.data) != layout.size:
            raise Cia402FrameError(
                can_id,
                f"{name} length",
                f"{len(message.data)} bytes, the mapping has {layout.size}",
            )
        fields = {
            key: value
            for key, value in zip(rpdo.keys, layout.unpack(message.data), strict=True)
            if key[0] not in DUMMIES  # another drive's bytes
        }
        mode = fields.get((MODE_OF_OPERATION, 0), MODE_NO_CHANGE)
        if mode != MODE_NO_CHANGE and mode not in MODES:
            raise Cia402FrameError(can_id, "mode of operation", f"{mode} is not 0, 8 or 10")
        if self.nmt_state is not NmtState.OPERATIONAL:
            self.counters.reject("RPDO outside OPERATIONAL")
            return []
        self.counters.accepted += 1
        if rpdo.deadline:
            self._expiry[can_id] = expiry = now + rpdo.deadline
            self._soonest = min(self._soonest, expiry)
        if rpdo.synchronous:
            self._pending[can_id] = fields
            return []
        return self._act(fields)

    def _act(self, fields: dict[tuple[int, int], int]) -> list[can.Message]:
        """An RPDO's fields (consumed) into the dictionary, then the controlword (if
        mapped)."""
        mode = fields.pop((MODE_OF_OPERATION, 0), MODE_NO_CHANGE)
        controlword = fields.pop((CONTROLWORD, 0), None)
        if mode != MODE_NO_CHANGE:
            self._set_mode(mode)
        self.values.update(fields)
        self.target_torque = self.values[(TARGET_TORQUE, 0)]
        self.target_position = self.values[(TARGET_POSITION, 0)]
        if controlword is None:
            self._apply()
            return []
        return self._control(controlword)

    def _set_mode(self, mode: int) -> None:
        """Mode of operation; entering mode 8 starts from the actual position (no jump to
        a stale 0x607A when no target comes with the switch)."""
        if mode == MODE_CSP and self.mode != MODE_CSP:
            self.values[(TARGET_POSITION, 0)] = self.target_position = self._position()
        self.values[(MODE_OF_OPERATION, 0)] = self.mode = mode

    # -- 402 state machine ------------------------------------------------------------------

    def _control(self, controlword: int) -> list[can.Message]:
        """Apply a controlword (from an RPDO, SDO or a 0x6007 reaction)."""
        previous, self.controlword = self.controlword, controlword
        self.values[(CONTROLWORD, 0)] = controlword
        out: list[can.Message] = []
        if self.state in _FAULTED:
            if controlword & CONTROL_FAULT_RESET and not previous & CONTROL_FAULT_RESET:
                out = self._fault_reset()
        else:
            command = decode_command(controlword)
            stopping = command is Command.QUICK_STOP and self.state is State.OPERATION_ENABLED
            if stopping and self.values.get((QUICK_STOP_OPTION_CODE, 0)) in QUICK_STOP_HOLD:
                self._brake_reaction()
            elif stopping:  # ramp, then power stage off: only a holding brake holds
                command = Command.DISABLE_VOLTAGE
                self.hold = BrakeMode.HOLDING_BRAKE if self.has_holding_brake else None
            self.state = next_state(self.state, command)
            released = command is Command.DISABLE_VOLTAGE and controlword & CONTROL_RELEASE_HOLD
            if self.state is State.OPERATION_ENABLED or (released and not stopping):
                self.hold = None
        self._apply()
        return out

    def _brake_reaction(self) -> None:
        """Latch the configured reaction if the power stage is on (an already latched
        reaction stays as it is: a position hold keeps its original length)."""
        if self.hold is not None or self.state is not State.OPERATION_ENABLED:
            return
        if self.brake_reaction is BrakeMode.HOLDING_BRAKE and self.has_holding_brake:
            self.hold = BrakeMode.HOLDING_BRAKE
        else:
            self.hold, self.hold_length = BrakeMode.POSITION_HOLD, self.length

    def _fault(self, code: int, text: str, persistent: bool) -> list[can.Message]:
        self._brake_reaction()
        self.state = State.FAULT
        self.fault_code, self.fault_text, self.fault_persistent = code, text, persistent
        self._apply()
        if self.nmt_state not in _SDO_STATES:
            return []
        return [encode_emcy(self.node_id, code, error_register(code))]

    def _fault_reset(self) -> list[can.Message]:
        if self.fault_persistent:
            return []
        self.state = State.SWITCH_ON_DISABLED
        self.fault_code, self.fault_text = 0, None
        return [encode_emcy(self.node_id, 0, 0)]

    def _watchdog(self, now: float) -> list[can.Message]:
        if now < self._soonest:
            return []
        out = []
        expired = [cob for cob, expiry in self._expiry.items() if now >= expiry]
        for cob in expired:
            del self._expiry[cob]  # off until that RPDO comes again
        if expired and self.state not in _FAULTED:
            pdo = self._rpdos[expired[0]].layout
            text = f"no {pdo.name} within its deadline 0x{pdo.comm_index:04X}:05"
            out = self._fault(RPDO_TIMEOUT, text, False)
        lost = [node for node, expiry in self._consumed.items() if now >= expiry]
        if lost:
            for node in lost:
                del self._consumed[node]
            out += self._connection_lost(f"no heartbeat from node {lost[0]} (0x1016)")
        self._soonest = min((*self._expiry.values(), *self._consumed.values()), default=math.inf)
        return out

    def _connection_lost(self, text: str) -> list[can.Message]:
        """Abort connection: EMCY 0x8130, then the 0x6007 reaction."""
        option = self.values.get((ABORT_CONNECTION_OPTION, 0), ABORT_FAULT)
        if option == ABORT_FAULT:
            return self._fault(HEARTBEAT_LOST, text, False)
        out = [encode_emcy(self.node_id, HEARTBEAT_LOST, error_register(HEARTBEAT_LOST))]
        if option == ABORT_QUICK_STOP:
            out += self._control(Command.QUICK_STOP.value)
        elif option == ABORT_DISABLE_VOLTAGE:
            self.hold = BrakeMode.HOLDING_BRAKE if self.has_holding_brake else None
            out += self._control(Command.DISABLE_VOLTAGE.value)
        return out

    def _torque_actual(self) -> int:
        """0x6077: the torque the power stage produces (per mille of rated torque), in
        torque control and in a position hold alike, as a drive's current sensing reports."""
        torque = self.scaling.motor_torque(self.produced, self.length)
        return max(-0x8000, min(0x7FFF, round(torque * 1000.0 / self.rated_torque)))

    def _apply(self) -> None:
        """The power stage and brake for the state, mode and latched reaction."""
        if self.state is State.OPERATION_ENABLED:
            self.brake_engaged = False
            if self.mode == MODE_CST:
                limit = self.max_torque
                torque = max(-limit, min(limit, self.target_torque))
                self.actuation = Actuation.TORQUE
                self.force = self.scaling.force(torque * self.rated_torque / 1000.0, self.length)
                self.target_length = math.nan
            else:
                self.actuation = Actuation.POSITION
                self.force = 0.0
                self.target_length = self.scaling.length(self.target_position)
        elif self.hold is BrakeMode.POSITION_HOLD:
            self.brake_engaged = False
            self.actuation = Actuation.POSITION
            self.force = 0.0
            self.target_length = self.hold_length
        else:
            self.brake_engaged = self.has_holding_brake
            self.actuation = Actuation.OFF
            self.force = 0.0
            self.target_length = math.nan

    # -- SDO server -------------------------------------------------------------------------

    def _on_sdo(self, message: can.Message, now: float) -> list[can.Message]:
        request = decode_sdo_request(message.arbitration_id, message.data)
        if self.nmt_state not in _SDO_STATES:
            self.counters.reject("SDO while stopped")
            return []
        self.counters.accepted += 1
        index, sub = request.index, request.subindex
        if request.kind is SdoKind.ABORT:
            self._transfer = None
            return []
        if request.kind in (SdoKind.SEGMENT, SdoKind.SEGMENT_ASK):
            return self._on_segment(request.kind, request.toggle, request.data, request.last, now)
        self._transfer = None
        if request.kind is SdoKind.UNSUPPORTED:
            return [self._abort(index, sub, ABORT_UNSUPPORTED_COMMAND)]
        var = self._variable(index, sub)
        if isinstance(var, int):
            return [self._abort(index, sub, var)]
        if request.kind is SdoKind.UPLOAD:
            if not var.readable:
                return [self._abort(index, sub, ABORT_READ_WRITE_ONLY)]
            key = (index, sub)
            live = self._live.get(key)
            value = live() if live is not None else self.values.get(key, self.strings.get(key))
            if value is None:  # an EDS object without a value
                return [self._abort(index, sub, ABORT_NO_DATA)]
            data = value if isinstance(value, bytes) else var.encode_raw(value)
            if len(data) > 4:
                self._transfer = ("upload", key, data, 0)
            return [encode_sdo_upload_response(self.node_id, index, sub, data)]
        if request.segmented:
            if not var.writable:
                return [self._abort(index, sub, ABORT_WRITE_READ_ONLY)]
            self._transfer = ("download", (index, sub), b"", 0)
            return [encode_sdo_download_response(self.node_id, index, sub)]
        data = request.data
        if not request.sized and (index, sub) not in self.strings:
            data = data[: len(var) // 8]  # CiA 301 expedited download, e=1 s=0
        return self._store(var, data, now)

    def _on_segment(
        self, kind: SdoKind, toggle: int, data: bytes, last: bool, now: float
    ) -> list[can.Message]:
        """The next segment of the open segmented transfer (CiA 301 toggle bit)."""
        transfer, self._transfer = self._transfer, None
        wanted = "upload" if kind is SdoKind.SEGMENT_ASK else "download"
        if transfer is None or transfer[0] != wanted:
            return [self._abort(0, 0, ABORT_UNSUPPORTED_COMMAND)]
        _, key, buffer, expected = transfer
        if toggle != expected:
            return [self._abort(*key, ABORT_TOGGLE)]
        if wanted == "upload":
            chunk, rest = buffer[:7], buffer[7:]
            if rest:
                self._transfer = ("upload", key, rest, toggle ^ 1)
            return [encode_sdo_segment(self.node_id, toggle, chunk, not rest, server=True)]
        buffer += data
        if not last:
            self._transfer = ("download", key, buffer, toggle ^ 1)
            return [encode_sdo_segment_ask(self.node_id, toggle, server=True)]
        var = self._variable(*key)
        assert not isinstance(var, int)
        out = self._store(var, buffer, now)
        if out and out[0].data[0] == 0x60:  # confirmed: the last segment's confirmation
            out[0] = encode_sdo_segment_ask(self.node_id, toggle, server=True)
        return out

    def _store(self, var: ODVariable, data: bytes, now: float) -> list[can.Message]:
        """A complete download: stored, or the abort."""
        index, sub = var.index, var.subindex
        code = self._write(var, data, now)
        if code:
            return [self._abort(index, sub, code)]
        out = [encode_sdo_download_response(self.node_id, index, sub)]
        if index == CONTROLWORD:
            out += self._control(self.values[(CONTROLWORD, 0)])
        return out

    def _abort(self, index: int, sub: int, code: int) -> can.Message:
        return encode_sdo_abort(self.node_id, index, sub, code, server=True)

    def _write(self, var: ODVariable, data: bytes, now: float) -> int:
        """Store an SDO download; the abort code (0: written)."""
        if not var.writable:
            return ABORT_WRITE_READ_ONLY
        key = (var.index, var.subindex)
        if key in self.strings:
            self.strings[key] = bytes(data)
            return 0
        if len(data) != len(var) // 8:
            return ABORT_LENGTH
        value = var.decode_raw(data)
        if var.min is not None and value < var.min:
            return ABORT_VALUE_LOW
        if var.max is not None and value > var.max:
            return ABORT_VALUE_HIGH
        if key == (MODE_OF_OPERATION, 0) and value not in (MODE_NO_CHANGE, *MODES):
            return ABORT_VALUE_RANGE
        code = self._pdo_write(key, value)
        if code:
            return code
        if key == (MODE_OF_OPERATION, 0):
            if value == MODE_NO_CHANGE:
                return 0
            self._set_mode(value)
        self.values[key] = value
        self._settings()
        if key == (PRODUCER_HEARTBEAT, 0):
            self._next_heartbeat = now + self.heartbeat_period if value else math.inf
        if key != (CONTROLWORD, 0):
            self._apply()
        return 0

    def _pdo_write(self, key: tuple[int, int], value: int) -> int:
        """CiA 301 rules for the PDO parameters; the abort code (0: allowed).  A mapping
        changes only while its PDO is invalid (COB-ID bit 31) and sub0 is 0; sub0 checks
        the entries; a valid COB-ID changes only through invalid."""
        index, sub = key
        if 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00:
            comm = index - 0x200
            if not self.values.get((comm, 1), PDO_INVALID) & PDO_INVALID:
                return ABORT_DEVICE_STATE
            if sub and self.values.get((index, 0), 0):
                return ABORT_DEVICE_STATE
            if sub == 0 and value:
                keys = []
                for k in range(1, value + 1):
                    entry = self.values.get((index, k), 0)
                    target = self.od.get(entry >> 16)
                    if target is None:
                        return ABORT_NOT_MAPPABLE
                    keys.append((entry >> 16, entry >> 8 & 0xFF))
                try:
                    layout = pdo_layout(self.od, index < 0x1800, (index & 0x1FF) + 1, keys, 0)
                except (KeyError, ValueError):
                    return ABORT_NOT_MAPPABLE
                if layout.struct.size > 8:
                    return ABORT_PDO_TOO_LONG
                for k, e in enumerate(layout.entries):
                    var = self.od[e.index] if not e.subindex else self.od[e.index][e.subindex]
                    usable = var.writable if index < 0x1800 else var.readable
                    mappable = var.pdo_mappable
                    if e.index in DUMMIES:  # in the OD only where [DummyUsage] allows it
                        mappable = usable = index < 0x1800  # RPDOs only
                    if (
                        not (mappable and usable)
                        or self.values[(index, k + 1)] & 0xFF != e.bits
                    ):
                        return ABORT_NOT_MAPPABLE
        elif (0x1400 <= index < 0x1600 or 0x1800 <= index < 0x1A00) and sub == 1:
            old = self.values.get(key, PDO_INVALID)
            if not old & PDO_INVALID and not value & PDO_INVALID and value != old:
                return ABORT_VALUE_RANGE
        return 0
