"""ODrive CANSimple frame codecs (firmware 0.6 semantics), host and device directions.

Arbitration id = node_id << 5 | cmd_id, 11-bit.  Payloads are little-endian; positions
are motor turns, velocities turns/s, torques N·m at the motor shaft, as float32.  The
layouts follow ODrive's CAN protocol page and are described, signal by signal, in
config/can/odrive_cansimple.dbc (tests check every frame against it).

Every frame carries the data length ODrive's DBC gives its message (`LENGTHS`: 8 bytes for
all but Estop, 0, and Clear_Errors, 1), unused bytes zero, as the firmware and ODrive's own
CAN libraries send them.  Decoders refuse a frame shorter than that length (longer ones,
up to 8, are read like the firmware: trailing bytes ignored) with `OdriveFrameError`, and
so a non-finite float or an out-of-range enum value.  A heartbeat's axis state outside
firmware 0.6's list is decoded all the same (an int, not an `AxisState`): the host reports
it as a fault instead of losing the axis' heartbeats.  `OdriveFrameError.reason`
("<Message>.<problem>") is the key drivers count rejects by.

Every encoder and decoder uses a precompiled `struct.Struct`: the hot path (torque
command, encoder estimate) costs one pack or unpack and one `can.Message`.
"""

from __future__ import annotations

import enum
import math
import struct
from functools import lru_cache
from typing import NamedTuple

import can

from drivers.base import FrameError, data_frame

NODE_ID_MAX = 63  # 6-bit node id
CMD_MASK = 0x1F
MAX_DLC = 8
FF_SCALE = 0.001  # Set_Input_Pos feed-forwards: int16 in units of 0.001 turn/s and 0.001 N·m
FLOAT32_MAX = 3.4028234663852886e38


class Cmd(enum.IntEnum):
    """The CANSimple command ids this project uses."""

    HEARTBEAT = 0x01
    ESTOP = 0x02
    GET_ERROR = 0x03
    SET_AXIS_STATE = 0x07
    GET_ENCODER_ESTIMATES = 0x09
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_POS = 0x0C
    SET_INPUT_TORQUE = 0x0E
    CLEAR_ERRORS = 0x18


# Message names as in ODrive's documentation and the DBC; reject reasons start with them.
MESSAGE_NAMES = {
    Cmd.HEARTBEAT: "Heartbeat",
    Cmd.ESTOP: "Estop",
    Cmd.GET_ERROR: "Get_Error",
    Cmd.SET_AXIS_STATE: "Set_Axis_State",
    Cmd.GET_ENCODER_ESTIMATES: "Get_Encoder_Estimates",
    Cmd.SET_CONTROLLER_MODE: "Set_Controller_Mode",
    Cmd.SET_INPUT_POS: "Set_Input_Pos",
    Cmd.SET_INPUT_TORQUE: "Set_Input_Torque",
    Cmd.CLEAR_ERRORS: "Clear_Errors",
}


class AxisState(enum.IntEnum):
    """ODrive 0.6.x AxisState, as ODrive's 0.6 DBC and the odrive package's enums list it
    (5, SENSORLESS_CONTROL, is in the DBC's value table only; 15 and 16 came with 0.6.x)."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    SENSORLESS_CONTROL = 5
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14
    HARMONIC_CALIBRATION = 15
    HARMONIC_CALIBRATION_COMMUTATION = 16


class ControlMode(enum.IntEnum):
    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(enum.IntEnum):
    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ProcedureResult(enum.IntEnum):
    """The heartbeat's procedure_result values the simulated drive reports."""

    SUCCESS = 0
    INVALID_STATE = 13


class AxisError(enum.IntFlag):
    """ODrive 0.6.x ODriveError bits, the heartbeat's axis_error and Get_Error's
    active_errors (0x20000 as odrive 0.6.11's enums name it; bits not listed show in hex).
    (0.5.x numbered axis errors differently: its WATCHDOG_TIMER_EXPIRED was 0x800, which
    0.6 uses for DC_BUS_OVER_REGEN_CURRENT.)"""

    INITIALIZING = 0x00000001
    SYSTEM_LEVEL = 0x00000002
    TIMING_ERROR = 0x00000004
    MISSING_ESTIMATE = 0x00000008
    BAD_CONFIG = 0x00000010
    DRV_FAULT = 0x00000020
    MISSING_INPUT = 0x00000040
    DC_BUS_OVER_VOLTAGE = 0x00000100
    DC_BUS_UNDER_VOLTAGE = 0x00000200
    DC_BUS_OVER_CURRENT = 0x00000400
    DC_BUS_OVER_REGEN_CURRENT = 0x00000800
    CURRENT_LIMIT_VIOLATION = 0x00001000
    MOTOR_OVER_TEMP = 0x00002000
    INVERTER_OVER_TEMP = 0x00004000
    VELOCITY_LIMIT_VIOLATION = 0x00008000
    POSITION_LIMIT_VIOLATION = 0x00010000
    REQUESTED_CURRENT_TOO_HIGH = 0x00020000
    WATCHDOG_TIMER_EXPIRED = 0x01000000
    ESTOP_REQUESTED = 0x02000000
    SPINOUT_DETECTED = 0x04000000
    BRAKE_RESISTOR_DISARMED = 0x08000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


_ERROR_BITS = tuple((int(flag), flag.name) for flag in AxisError)
_AXIS_STATES: tuple[AxisState | None, ...] = tuple(
    AxisState._value2member_map_.get(value) for value in range(256)
)


@lru_cache(maxsize=256)
def error_text(code: int) -> str:
    """Readable names of the error bits set in `code` ("A|B"); unknown bits in hex."""
    names = [name for bit, name in _ERROR_BITS if code & bit]
    unknown = code & ~sum(bit for bit, _ in _ERROR_BITS)
    if unknown:
        names.append(f"0x{unknown:08X}")
    return "|".join(names) if names else "none"


class OdriveFrameError(FrameError):
    """A malformed CANSimple frame.  `reason` ("<Message>.<problem>") is the reject key."""

    def __init__(self, message: can.Message, cmd: int, problem: str, detail: str) -> None:
        name = MESSAGE_NAMES.get(cmd, f"cmd 0x{cmd:02X}")
        super().__init__(
            f"{name} frame 0x{message.arbitration_id:03X} (node {message.arbitration_id >> 5}): "
            f"{detail}"
        )
        self.reason = f"{name}.{problem}"


def frame_id(node_id: int, cmd: int) -> int:
    """The 11-bit arbitration id of command `cmd` for node `node_id`."""
    if not 0 <= node_id <= NODE_ID_MAX:
        raise ValueError(f"ODrive node ids run 0..{NODE_ID_MAX}, not {node_id}")
    return node_id << 5 | cmd


# -- payload layouts -------------------------------------------------------------------

# data length of each message in ODrive's DBC (config/can/odrive_cansimple.dbc)
LENGTHS = {
    Cmd.HEARTBEAT: 8,
    Cmd.ESTOP: 0,
    Cmd.GET_ERROR: 8,
    Cmd.SET_AXIS_STATE: 8,
    Cmd.GET_ENCODER_ESTIMATES: 8,
    Cmd.SET_CONTROLLER_MODE: 8,
    Cmd.SET_INPUT_POS: 8,
    Cmd.SET_INPUT_TORQUE: 8,
    Cmd.CLEAR_ERRORS: 1,
}
# axis_error, axis_state, procedure_result, trajectory_done (bit 0), reserved byte
HEARTBEAT = struct.Struct("<IBBBx")
U32 = struct.Struct("<I4x")  # Set_Axis_State
TWO_U32 = struct.Struct("<II")  # Set_Controller_Mode, Get_Error
TWO_F32 = struct.Struct("<ff")  # Get_Encoder_Estimates
F32 = struct.Struct("<f4x")  # Set_Input_Torque
INPUT_POS = struct.Struct("<fhh")  # input_pos, vel_ff, torque_ff
U8 = struct.Struct("<B")  # Clear_Errors identify


def _message(node_id: int, cmd: int, data: bytes) -> can.Message:
    return data_frame(frame_id(node_id, cmd), data)


def _float32(value: float, what: str) -> float:
    if not -FLOAT32_MAX <= value <= FLOAT32_MAX:  # also false for NaN
        raise FrameError(f"{what} = {value} is not a finite float32")
    return value


def _payload(message: can.Message, cmd: Cmd) -> bytearray:
    data = message.data
    size = LENGTHS[cmd]
    if not size <= len(data) <= MAX_DLC:
        raise OdriveFrameError(
            message, cmd, "dlc", f"{len(data)} data bytes, expected {size}..{MAX_DLC}"
        )
    return data


def _finite(message: can.Message, cmd: int, *values: float) -> None:
    for value in values:
        if not math.isfinite(value):
            raise OdriveFrameError(message, cmd, "non_finite", f"non-finite value {value}")


# -- drive -> host ---------------------------------------------------------------------


class Heartbeat(NamedTuple):
    axis_error: int
    axis_state: AxisState | int  # an int: a state firmware 0.6 does not list
    procedure_result: int
    trajectory_done: bool


def encode_heartbeat(
    node_id: int,
    axis_error: int,
    axis_state: AxisState,
    procedure_result: int = 0,
    trajectory_done: bool = True,
) -> can.Message:
    return _message(
        node_id,
        Cmd.HEARTBEAT,
        HEARTBEAT.pack(axis_error, axis_state, procedure_result, trajectory_done),
    )


def decode_heartbeat(message: can.Message) -> Heartbeat:
    error, state, result, done = HEARTBEAT.unpack_from(_payload(message, Cmd.HEARTBEAT))
    axis_state = _AXIS_STATES[state]
    return Heartbeat(error, state if axis_state is None else axis_state, result, bool(done & 1))


def encode_encoder_estimates(node_id: int, pos: float, vel: float) -> can.Message:
    """pos in turns, vel in turns/s."""
    data = TWO_F32.pack(_float32(pos, "pos_estimate"), _float32(vel, "vel_estimate"))
    return _message(node_id, Cmd.GET_ENCODER_ESTIMATES, data)


def decode_encoder_estimates(message: can.Message) -> tuple[float, float]:
    pos, vel = TWO_F32.unpack_from(_payload(message, Cmd.GET_ENCODER_ESTIMATES))
    _finite(message, Cmd.GET_ENCODER_ESTIMATES, pos, vel)
    return pos, vel


def encode_error_status(node_id: int, active_errors: int, disarm_reason: int) -> can.Message:
    """The drive's answer to a Get_Error request."""
    return _message(node_id, Cmd.GET_ERROR, TWO_U32.pack(active_errors, disarm_reason))


def decode_error_status(message: can.Message) -> tuple[int, int]:
    """(active_errors, disarm_reason) from a Get_Error answer."""
    return TWO_U32.unpack_from(_payload(message, Cmd.GET_ERROR))


# -- host -> drive ---------------------------------------------------------------------


def encode_request(node_id: int, cmd: Cmd) -> can.Message:
    """A remote (RTR) frame asking the drive for message `cmd` (heartbeat, estimates,
    errors); DLC is the answer's, as CAN requires of remote frames."""
    return can.Message(
        arbitration_id=frame_id(node_id, cmd), is_extended_id=False, is_remote_frame=True, dlc=8
    )


def is_error_request(message: can.Message) -> bool:
    """A Get_Error request: remote frame, or data frame of 0 or 1 byte (error type 0)."""
    data = message.data
    return message.is_remote_frame or len(data) == 0 or (len(data) == 1 and data[0] == 0)


def encode_estop(node_id: int) -> can.Message:
    return _message(node_id, Cmd.ESTOP, b"")


def encode_set_axis_state(node_id: int, state: AxisState) -> can.Message:
    return _message(node_id, Cmd.SET_AXIS_STATE, U32.pack(state))


def decode_set_axis_state(message: can.Message) -> AxisState:
    (state,) = U32.unpack_from(_payload(message, Cmd.SET_AXIS_STATE))
    axis_state = _AXIS_STATES[state] if state < 256 else None
    if axis_state is None:
        raise OdriveFrameError(
            message, Cmd.SET_AXIS_STATE, "axis_state", f"unknown axis state {state}"
        )
    return axis_state


def encode_set_controller_mode(
    node_id: int, control_mode: ControlMode, input_mode: InputMode
) -> can.Message:
    return _message(node_id, Cmd.SET_CONTROLLER_MODE, TWO_U32.pack(control_mode, input_mode))


def decode_set_controller_mode(message: can.Message) -> tuple[ControlMode, InputMode]:
    control, inputs = TWO_U32.unpack_from(_payload(message, Cmd.SET_CONTROLLER_MODE))
    if control not in ControlMode._value2member_map_:
        raise OdriveFrameError(
            message, Cmd.SET_CONTROLLER_MODE, "control_mode", f"unknown control mode {control}"
        )
    if inputs not in InputMode._value2member_map_:
        raise OdriveFrameError(
            message, Cmd.SET_CONTROLLER_MODE, "input_mode", f"unknown input mode {inputs}"
        )
    return ControlMode(control), InputMode(inputs)


def input_pos_payload(pos: float, vel_ff: float = 0.0, torque_ff: float = 0.0) -> bytes:
    """Set_Input_Pos data: pos (turns) float32, feed-forwards (turns/s, N·m) as int16 of
    0.001 units, rounded (beyond the int16 range is a FrameError, not clamped)."""
    return INPUT_POS.pack(
        _float32(pos, "input_pos"), _int16(vel_ff, "vel_ff"), _int16(torque_ff, "torque_ff")
    )


def _int16(value: float, what: str) -> int:
    units = round(value / FF_SCALE) if math.isfinite(value) else None
    if units is None or not -32768 <= units <= 32767:
        raise FrameError(f"Set_Input_Pos {what} = {value} outside -32.768..32.767")
    return units


def encode_set_input_pos(
    node_id: int, pos: float, vel_ff: float = 0.0, torque_ff: float = 0.0
) -> can.Message:
    return _message(node_id, Cmd.SET_INPUT_POS, input_pos_payload(pos, vel_ff, torque_ff))


def decode_set_input_pos(message: can.Message) -> tuple[float, float, float]:
    """(pos turns, vel_ff turns/s, torque_ff N·m)."""
    pos, vel_ff, torque_ff = INPUT_POS.unpack_from(_payload(message, Cmd.SET_INPUT_POS))
    _finite(message, Cmd.SET_INPUT_POS, pos)
    return pos, vel_ff * FF_SCALE, torque_ff * FF_SCALE


def encode_set_input_torque(node_id: int, torque: float) -> can.Message:
    """torque in N·m at the motor shaft."""
    return _message(node_id, Cmd.SET_INPUT_TORQUE, F32.pack(_float32(torque, "input_torque")))


def decode_set_input_torque(message: can.Message) -> float:
    (torque,) = F32.unpack_from(_payload(message, Cmd.SET_INPUT_TORQUE))
    _finite(message, Cmd.SET_INPUT_TORQUE, torque)
    return torque


def encode_clear_errors(node_id: int, identify: bool = False) -> can.Message:
    return _message(node_id, Cmd.CLEAR_ERRORS, U8.pack(identify))


def decode_clear_errors(message: can.Message) -> bool:
    """The identify flag (blink the LED)."""
    return bool(_payload(message, Cmd.CLEAR_ERRORS)[0] & 1)
