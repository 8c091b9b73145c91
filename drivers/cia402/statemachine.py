"""The CiA 402 power state machine: statusword decoding, controlword commands, transitions.

Shared by the host driver (which reads statuswords and writes controlwords) and the
simulated drive (which runs the transitions), so both sides agree by construction.

Two manufacturer-specific bits of the simulated drive (documented in the EDS):
- statusword bit 14 (`STATUS_HOLD`): the drive's own brake reaction is latched (it holds
  its cable at the length it had when a fault, RPDO timeout or quick stop struck, or has
  its holding brake engaged), also in states where 402 would switch the power stage off.
- controlword bit 15 (`CONTROL_RELEASE_HOLD`): with "disable voltage", releases that latch
  and really switches the power stage off (only for a resting or mechanically braked load).
"""

from __future__ import annotations

import enum

from drivers.base import DriveState

MODE_CSP = 8  # cyclic synchronous position (0x6060): the position hold
MODE_CST = 10  # cyclic synchronous torque (0x6060): force control
MODES = (MODE_CSP, MODE_CST)
MODE_NO_CHANGE = 0  # 0x6060 = 0 in an RPDO: keep the present mode (402)
COMMANDED_MODES = (MODE_NO_CHANGE, MODE_CSP, MODE_CST)

STATUS_WARNING = 1 << 7
STATUS_REMOTE = 1 << 9
STATUS_HOLD = 1 << 14
CONTROL_FAULT_RESET = 1 << 7
CONTROL_RELEASE_HOLD = 1 << 15


class State(enum.IntEnum):
    """402 power states; the value is the statusword pattern of bits 0-3, 5, 6."""

    NOT_READY_TO_SWITCH_ON = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08


class Command(enum.Enum):
    """Device-control commands (402 table 'device control commands'); value = the
    controlword the host sends for it.  DISABLE_OPERATION and SWITCH_ON share a pattern
    (0x07): which transition it makes depends on the state."""

    SHUTDOWN = 0x06
    SWITCH_ON = 0x07
    ENABLE_OPERATION = 0x0F
    DISABLE_VOLTAGE = 0x00
    QUICK_STOP = 0x02
    FAULT_RESET = 0x80


DISABLE_OPERATION = Command.SWITCH_ON


def _status_table() -> list[State | None]:
    """statusword & 0x6F -> State (None: a pattern 402 does not define).  Bit 5 (quick
    stop) is part of the pattern only in the powered states."""
    table: list[State | None] = [None] * 0x70
    for word in range(0x70):
        for state in State:
            mask = 0x6F if state.value & 0x20 or state is State.QUICK_STOP_ACTIVE else 0x4F
            if word & mask == state.value:
                table[word] = state
    return table


_STATUS_TABLE = _status_table()

_POWERED = (
    State.READY_TO_SWITCH_ON,
    State.SWITCHED_ON,
    State.OPERATION_ENABLED,
    State.QUICK_STOP_ACTIVE,
)


def decode_statusword(statusword: int) -> State | None:
    """The 402 state a statusword reports, or None for an undefined bit pattern."""
    return _STATUS_TABLE[statusword & 0x6F]


def encode_statusword(state: State, hold: bool = False) -> int:
    """The statusword of a drive in `state` (remote bit set; voltage-enabled bit 4 in the
    powered states; bit 14 when its own brake reaction is latched)."""
    word = state.value | STATUS_REMOTE
    if state in _POWERED:
        word |= 0x10
    if hold:
        word |= STATUS_HOLD
    return word


def decode_command(controlword: int) -> Command | None:
    """The level command of a controlword (bit 7 set: none, the fault reset is an edge)."""
    if controlword & 0x82 == 0x00:
        return Command.DISABLE_VOLTAGE
    if controlword & 0x86 == 0x02:
        return Command.QUICK_STOP
    if controlword & 0x87 == 0x06:
        return Command.SHUTDOWN
    if controlword & 0x8F == 0x07:
        return Command.SWITCH_ON
    if controlword & 0x8F == 0x0F:
        return Command.ENABLE_OPERATION
    return None


# (state, command) -> next state; pairs not listed leave the state unchanged.  The
# quick stop option code of the simulated drive stays in QUICK STOP ACTIVE (5-8 style),
# so ENABLE_OPERATION returns from it (transition 16).
_TRANSITIONS: dict[tuple[State, Command], State] = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 2
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): State.SWITCHED_ON,  # 3
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 3+4
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 7
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 7
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 4
    (State.SWITCHED_ON, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 6
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 10
    (State.SWITCHED_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,  # 10
    (State.OPERATION_ENABLED, Command.SWITCH_ON): State.SWITCHED_ON,  # 5 (disable op.)
    (State.OPERATION_ENABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,  # 8
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 9
    (State.OPERATION_ENABLED, Command.QUICK_STOP): State.QUICK_STOP_ACTIVE,  # 11
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,  # 12
    (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,  # 16
}


def next_state(state: State, command: Command | None) -> State:
    """The state after a level command (faults and fault reset are handled by the drive:
    they depend on the fault's cause, not on the controlword alone)."""
    if command is None:
        return state
    return _TRANSITIONS.get((state, command), state)


def drive_state(state: State | None, mode: int = MODE_CST, hold: bool = False) -> DriveState:
    """The protocol-independent view of a 402 state (mode: 0x6061 display; hold: bit 14)."""
    if state is None:
        return DriveState.UNKNOWN
    if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
        return DriveState.FAULT
    if state is State.OPERATION_ENABLED:
        return DriveState.HOLDING if mode == MODE_CSP else DriveState.ENABLED
    if hold or state is State.QUICK_STOP_ACTIVE:
        return DriveState.HOLDING
    if state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
        return DriveState.READY
    return DriveState.DISABLED
