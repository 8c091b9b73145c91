"""Host side of CiA 402 drives in cyclic synchronous torque (CST) mode on one CANopen bus.

Cycle (Timing.SYNC): `cycle_start` sends SYNC; every drive answers with TPDO1 (statusword,
position, mode display) then TPDO2 (velocity).  `receive` returns a cable's index when a
TPDO2 completes a TPDO1 received since the latest SYNC: feedback is complete for the cycle.
A TPDO2 without such a TPDO1 (stale, or its TPDO1 lost) is counted as rejected and
dropped.  `commands` sends one RPDO1 per drive (controlword "enable operation", target
torque in per mille of the rated torque, mode 10).

Torque: force f (N along +l) -> motor torque Scaling.motor_torque(f) -> per mille of
`rated_torque`, rounded to the nearest per mille and clamped to +- the drive's max
torque 0x6072 (read at start-up, EDS default before); clamps are counted in
`torque_limited`.  A non-finite force raises FrameError (the caller brakes instead).

Brake (DESIGN §9; never a quick stop, which only ramps torque to zero and lets a
suspended platform fall):
- POSITION_HOLD: RPDO2 with "enable operation", mode 8 (cyclic synchronous position) and
  the current length as target position; one frame per drive, acted on at reception.
  The lengths are the host's trusted ones (never a raw frame's value, which may be
  forged): a non-finite or out-of-range one means none is trusted for that drive, which
  was then never enabled by this host, and it gets the power-stage-off frame below.
- HOLDING_BRAKE: RPDO1 with "disable operation" (OPERATION ENABLED -> SWITCHED ON), zero
  torque: the drive engages its holding brake as its power stage goes off.  Asked of a
  bus whose drives have no holding brake, brake() holds position instead.
`brake` never raises and needs no answer; `keepalive` repeats the latest brake, disable or
enable frames each cycle so the drives' RPDO deadline stays fed.

Start-up (SDO expedited transfers, own small codec since canopen's SDO client blocks on
a thread): NMT pre-operational, device type and PDO configuration checked against the
codec, holding brake and rated torque checked against the config, then 0x1005 SYNC
COB-ID, 0x1017 heartbeat, 0x1400:05 RPDO deadline, 0x6060 = 10 and 0x2000 brake reaction
written, NMT start, operational heartbeats awaited, and the 402 machine driven to
SWITCHED ON.  A drive found in FAULT or QUICK STOP ACTIVE is left as it is (it holds by
its own reaction); one found OPERATION ENABLED is refused: it may be holding a load for
another master.  The cyclic path never uses SDO.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

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
)
from drivers.cia402.codec import (
    BRAKE_REACTION,
    COB_ID_SYNC,
    CONTROLWORD,
    DEVICE_PROFILE_402,
    DEVICE_TYPE,
    EDS_PATH,
    EMCY_BASE,
    ERROR_CODE,
    HEARTBEAT_BASE,
    HOLDING_BRAKE_FITTED,
    I32_MAX,
    I32_MIN,
    MAX_TORQUE,
    MODE_OF_OPERATION,
    PDO_LAYOUTS,
    PRODUCER_HEARTBEAT,
    RATED_TORQUE,
    RPDO1,
    RPDO1_BASE,
    RPDO2,
    RPDO2_BASE,
    RPDO_DEADLINE_SUB,
    SDO_RESPONSE_BASE,
    STATUSWORD,
    SYNC_ID,
    TPDO1_BASE,
    TPDO2_BASE,
    Cia402FrameError,
    NmtCommand,
    NmtState,
    SdoKind,
    abort_text,
    check_eds,
    decode_emcy,
    decode_heartbeat,
    decode_sdo_response,
    decode_tpdo1,
    decode_tpdo2,
    emcy_text,
    encode_nmt,
    encode_sdo_download_request,
    encode_sdo_upload_request,
    encode_sync,
    load_eds,
    od_value,
    od_variable,
)
from drivers.cia402.statemachine import (
    CONTROL_RELEASE_HOLD,
    DISABLE_OPERATION,
    MODE_CSP,
    MODE_CST,
    STATUS_HOLD,
    Command,
    State,
    decode_statusword,
    drive_state,
)
from drivers.config import DrivesConfig

_FAULTED = (State.FAULT, State.FAULT_REACTION_ACTIVE)
_ENABLE = Command.ENABLE_OPERATION.value
_RPDO1_PACK = RPDO1.struct.pack
_RPDO2_PACK = RPDO2.struct.pack
_Message = can.Message
_isfinite = math.isfinite


class Cia402Driver(ActuatorDriver):
    """All CiA 402 drives of one bus, in cable order (`config.nodes[i]` drives cable i)."""

    timing = Timing.SYNC
    sdo_timeout = 0.1  # s to wait for each SDO answer
    state_polls = 100  # statusword reads while waiting for one 402 transition
    enable_timeout = 1.0  # s for every drive to report OPERATION ENABLED after enable()

    def __init__(
        self, config: DrivesConfig, scalings: Sequence[Scaling], eds: str | Path = EDS_PATH
    ) -> None:
        if config.protocol != "cia402":
            raise ValueError(f"Cia402Driver needs protocol cia402, config says {config.protocol}")
        super().__init__(scalings)
        if len(config.nodes) != self.n:
            raise ValueError(f"{self.n} scalings for {len(config.nodes)} drives")
        self.config = config
        self.nodes = list(config.nodes)
        self.eds = Path(eds)
        for node in self.nodes:
            problems = check_eds(load_eds(self.eds, node), node)
            if problems:
                raise ValueError(
                    f"{self.eds} does not match the CiA 402 codec: {'; '.join(problems)}"
                )
        self.od = load_eds(self.eds, self.nodes[0])
        rated = config.rated_torque
        assert rated is not None  # DrivesConfig requires it for cia402
        # per mille of rated torque per newton along +l, per cable
        self._permille = [s.motor_torque(1.0) / rated * 1000.0 for s in self.scalings]
        self.max_torque = [int(od_value(od_variable(self.od, MAX_TORQUE)))] * self.n
        self.torque_limited = [0] * self.n  # commands clamped to +-max_torque
        self.nmt_state: list[NmtState | None] = [None] * self.n
        self._started = [False] * self.n
        # a started drive left OPERATIONAL (boot-up or NMT change): it lost its
        # configuration and, after a reboot, its position; a FAULT until start() again
        self._lost = [False] * self.n
        self._rpdo1 = [RPDO1_BASE + node for node in self.nodes]
        self._rpdo2 = [RPDO2_BASE + node for node in self.nodes]
        self._routes: dict[int, tuple[Callable[[int, int, bytearray, float], int | None], int]] = {}
        for i, node in enumerate(self.nodes):
            self._routes[TPDO1_BASE + node] = (self._on_tpdo1, i)
            self._routes[TPDO2_BASE + node] = (self._on_tpdo2, i)
            self._routes[EMCY_BASE + node] = (self._on_emcy, i)
            self._routes[HEARTBEAT_BASE + node] = (self._on_heartbeat, i)
        # feedback pairing: SYNCs sent, and the SYNC count at each pending TPDO1 (-1: none)
        self._epoch = 0
        self._position_epoch = [-1] * self.n
        self.position: list[int | None] = [None] * self.n  # last position actual (increments)
        self._standing: list[tuple[int, bytes]] = []  # frames keepalive() repeats

    # -- cycle ----------------------------------------------------------------------------

    def cycle_start(self) -> list[can.Message]:
        self._epoch += 1
        return [encode_sync()]

    def commands(self, forces: Sequence[float]) -> list[can.Message]:
        if len(forces) != self.n:
            raise FrameError(f"{len(forces)} forces for {self.n} CiA 402 drives")
        frames = []
        permille, limits, ids = self._permille, self.max_torque, self._rpdo1
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
            frames.append(
                _Message(
                    arbitration_id=ids[i],
                    data=_RPDO1_PACK(_ENABLE, torque, MODE_CST),
                    is_extended_id=False,
                )
            )
        self._standing = []
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
                standing.append((self._rpdo2[i], _RPDO2_PACK(_ENABLE, target, MODE_CSP)))
            else:
                standing.append((self._rpdo1[i], _RPDO1_PACK(DISABLE_OPERATION.value, 0, MODE_CST)))
        self._standing = standing
        return self.keepalive()

    def disable(self) -> list[can.Message]:
        """Disable voltage with the release-hold bit: every power stage off, also a
        drive holding by its own fault reaction; holding brakes engage where fitted."""
        word = Command.DISABLE_VOLTAGE.value | CONTROL_RELEASE_HOLD
        self._standing = [(can_id, _RPDO1_PACK(word, 0, MODE_CST)) for can_id in self._rpdo1]
        return self.keepalive()

    def keepalive(self) -> list[can.Message]:
        """The latest brake/disable/enable frames again (none after torque commands: a
        torque command is never repeated, the drive's RPDO deadline brakes instead)."""
        return [
            _Message(arbitration_id=can_id, data=data, is_extended_id=False)
            for can_id, data in self._standing
        ]

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

    def _on_tpdo1(self, i: int, can_id: int, data: bytearray, now: float) -> None:
        statusword, position, mode = decode_tpdo1(can_id, data)
        self.counters.accepted += 1
        self._update_state(i, statusword, mode)
        self.position[i] = position
        self._position_epoch[i] = self._epoch

    def _on_tpdo2(self, i: int, can_id: int, data: bytearray, now: float) -> int | None:
        """TPDO2 completes the sample whose TPDO1 came since the latest SYNC (a drive
        sends TPDO1 first, and its id wins arbitration); any other TPDO2 is stale."""
        velocity = decode_tpdo2(can_id, data)
        if self._position_epoch[i] != self._epoch:
            self.counters.reject("TPDO2 without TPDO1 since SYNC")
            return None
        self.counters.accepted += 1
        self._position_epoch[i] = -1
        scaling, feedback = self.scalings[i], self.feedback[i]
        feedback.length = scaling.length(self.position[i])
        feedback.rate = scaling.rate(velocity)
        feedback.stamp = now
        feedback.count += 1
        return i

    def _update_state(self, i: int, statusword: int, mode: int) -> None:
        status = self.status[i]
        state = drive_state(decode_statusword(statusword), mode, bool(statusword & STATUS_HOLD))
        if status.fault_code or self._lost[i]:
            # An EMCY is a fault (DESIGN §9) even while the statusword looks healthy: it
            # stays until an error-reset EMCY (code 0) or reset_faults.  So does a restart
            # (a boot-up heartbeat, even a forged one), until start() runs again.
            state = DriveState.FAULT
        status.state = state
        if state is DriveState.FAULT and status.fault is None:
            status.fault = "statusword reports FAULT (no EMCY received)"

    def _on_emcy(self, i: int, can_id: int, data: bytearray, now: float) -> None:
        code, register, _ = decode_emcy(can_id, data)
        self.counters.accepted += 1
        status = self.status[i]
        if code == 0:  # error reset: the state follows from the next statusword
            status.fault, status.fault_code = None, 0
        else:
            status.state = DriveState.FAULT
            status.fault = f"{emcy_text(code)} (error register 0x{register:02X})"
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

    async def start(self, link: Link, now: Callable[[], float]) -> None:
        config = self.config
        writes = (
            (COB_ID_SYNC, 0, SYNC_ID),
            (PRODUCER_HEARTBEAT, 0, max(1, round(config.heartbeat_period * 1000))),
            (RPDO1.comm_index, RPDO_DEADLINE_SUB, max(1, round(config.watchdog_timeout * 1000))),
            (MODE_OF_OPERATION, 0, MODE_CST),
            (BRAKE_REACTION, 0, int(config.brake is BrakeMode.HOLDING_BRAKE)),
        )
        for i, node in enumerate(self.nodes):
            self._started[i] = self._lost[i] = False
            link.send(encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, node))
            device_type = await self._read(link, i, DEVICE_TYPE)
            if device_type & 0xFFFF != DEVICE_PROFILE_402:
                raise DriverError(
                    f"node {node}: device type 0x{device_type:08X} is no CiA 402 drive"
                )
            if await self._read_state(link, i) is State.OPERATION_ENABLED:
                raise DriverError(
                    f"node {node}: operation is enabled (another master?); not taking over a "
                    "drive that may hold a load: let its RPDO deadline brake it first"
                )
            for index, sub, expected, what in self._pdo_checks(node):
                value = await self._read(link, i, index, sub)
                if value != expected:
                    raise DriverError(
                        f"node {node}: {what} is 0x{value:X}, the CiA 402 codec needs "
                        f"0x{expected:X} ({self.eds.name})"
                    )
            fitted = bool(await self._read(link, i, HOLDING_BRAKE_FITTED))
            if fitted != config.has_holding_brake:
                raise DriverError(
                    f"node {node}: the drive says holding brake fitted={fitted}, "
                    f"config has_holding_brake={config.has_holding_brake}"
                )
            rated = await self._read(link, i, RATED_TORQUE) / 1000.0
            if abs(rated - config.rated_torque) > 0.005 * config.rated_torque:
                raise DriverError(
                    f"node {node}: motor rated torque 0x6076 is {rated} N·m, "
                    f"config rated_torque is {config.rated_torque} N·m"
                )
            self.max_torque[i] = await self._read(link, i, MAX_TORQUE)
            for index, sub, value in writes:
                await self._write(link, i, index, sub, value)
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
        self._standing = []

    async def enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
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
            (self._rpdo2[i], _RPDO2_PACK(_ENABLE, target, MODE_CSP))
            for i, target in enumerate(targets)
        ]
        round_timeout = min(0.02, self.config.watchdog_timeout / 2)
        pending = set(range(self.n))
        seen: dict[int, tuple[State | None, int]] = {}
        for _ in range(max(1, math.ceil(self.enable_timeout / round_timeout))):
            for frame in self.keepalive() + self.cycle_start():
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

    async def reset_faults(self, link: Link) -> None:
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
        """Stop repeating brake/enable frames to drive i (keepalive)."""
        mine = (self._rpdo1[i], self._rpdo2[i])
        self._standing = [(can_id, data) for can_id, data in self._standing if can_id not in mine]

    def _names(self, indices: Iterable[int]) -> str:
        return ", ".join(str(self.nodes[i]) for i in sorted(indices))

    def _require_started(self, i: int) -> None:
        if not self._started[i]:
            raise DriverError(
                f"node {self.nodes[i]} is not started ({self.status[i].fault or 'start() not run'})"
            )

    def _pdo_checks(self, node: int) -> list[tuple[int, int, int, str]]:
        """(index, sub, value the codec needs, what) for the drive's PDO configuration."""
        checks = []
        for layout in PDO_LAYOUTS:
            comm, mapping = layout.comm_index, layout.map_index
            checks.append((comm, 1, layout.cob_id(node), f"{layout.name} COB-ID 0x{comm:04X}:01"))
            checks.append((comm, 2, layout.transmission_type, f"{layout.name} transmission type"))
            checks.append((mapping, 0, len(layout.entries), f"{layout.name} mapped object count"))
            checks.extend(
                (
                    mapping,
                    k + 1,
                    entry.mapping,
                    f"{layout.name} mapping 0x{mapping:04X}:{k + 1:02X}",
                )
                for k, entry in enumerate(layout.entries)
            )
        return checks

    def _sdo_reply(self, node: int, index: int, sub: int) -> Callable[[can.Message], bool]:
        can_id, head = SDO_RESPONSE_BASE + node, bytes((index & 0xFF, index >> 8, sub))

        def match(message: can.Message) -> bool:
            data = message.data
            return (
                message.arbitration_id == can_id
                and not message.is_extended_id
                and len(data) == 8
                and data[1:4] == head
                and data[0] >> 5 in (2, 3, 4)
            )

        return match

    async def _transfer(self, link: Link, i: int, request: can.Message, what: str) -> bytes:
        node = self.nodes[i]
        index, sub = request.data[1] | request.data[2] << 8, request.data[3]
        link.send(request)
        reply = await link.expect(self._sdo_reply(node, index, sub), self.sdo_timeout, what)
        sdo = decode_sdo_response(reply.arbitration_id, reply.data)
        if sdo.kind is SdoKind.ABORT:
            raise DriverError(f"{what} aborted: {abort_text(sdo.abort_code)}")
        return sdo.data if sdo.kind is SdoKind.UPLOAD else b""

    async def _read(self, link: Link, i: int, index: int, sub: int = 0) -> int:
        node, var = self.nodes[i], od_variable(self.od, index, sub)
        what = f"node {node}: SDO read 0x{index:04X}:{sub:02X} ({var.name})"
        data = await self._transfer(link, i, encode_sdo_upload_request(node, index, sub), what)
        if len(data) != len(var) // 8:
            raise DriverError(f"{what}: {len(data)} bytes, the object has {len(var) // 8}")
        return int(var.decode_raw(data))

    async def _write(self, link: Link, i: int, index: int, sub: int, value: int) -> None:
        node, var = self.nodes[i], od_variable(self.od, index, sub)
        what = f"node {node}: SDO write 0x{index:04X}:{sub:02X} ({var.name}) = {value}"
        request = encode_sdo_download_request(node, index, sub, var.encode_raw(value))
        await self._transfer(link, i, request, what)

    async def _read_state(self, link: Link, i: int) -> State:
        statusword = await self._read(link, i, STATUSWORD)
        state = decode_statusword(statusword)
        if state is None:
            raise DriverError(
                f"node {self.nodes[i]}: statusword 0x{statusword:04X} is no CiA 402 state"
            )
        return state

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
        self._update_state(i, await self._read(link, i, STATUSWORD), MODE_CST)
        if status.state is DriveState.FAULT:
            code = await self._read(link, i, ERROR_CODE)
            status.fault, status.fault_code = emcy_text(code), code

    async def _await_heartbeats(self, link: Link, now: Callable[[], float]) -> None:
        pending = set(range(self.n))
        index = {HEARTBEAT_BASE + node: i for i, node in enumerate(self.nodes)}

        def match(message: can.Message) -> bool:
            i = index.get(message.arbitration_id)
            if i is not None and not message.is_extended_id and bytes(message.data) == b"\x05":
                self.status[i].heartbeat_stamp = now()
                pending.discard(i)
            return not pending

        timeout = self.config.heartbeat_timeout
        try:
            await link.expect(match, timeout, "operational heartbeats from the CiA 402 nodes")
        except DriverError as exc:
            raise DriverError(
                f"no operational heartbeat from node(s) {self._names(pending)} within {timeout} s"
            ) from exc

    def _enabled_collector(
        self, pending: set[int], seen: dict[int, tuple[State | None, int]]
    ) -> Callable[[can.Message], bool]:
        """Match that records TPDO1 states and is true once every pending drive reports
        OPERATION ENABLED in mode 8."""
        index = {TPDO1_BASE + node: i for i, node in enumerate(self.nodes)}

        def match(message: can.Message) -> bool:
            i = index.get(message.arbitration_id)
            if i is not None and not message.is_extended_id:
                try:
                    statusword, _, mode = decode_tpdo1(message.arbitration_id, message.data)
                except FrameError:
                    return False
                seen[i] = (decode_statusword(statusword), mode)
                if seen[i] == (State.OPERATION_ENABLED, MODE_CSP):
                    pending.discard(i)
            return not pending

        return match
