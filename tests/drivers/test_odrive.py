"""ODrive CANSimple codecs against the DBC, and the host driver's frames and decoding.

Host <-> simulated drive sequences are in test_odrive_device.py.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import can
import cantools
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr.description import ConfigError
from drivers.base import BrakeMode, DriveState, FrameError, Scaling, Timing
from drivers.config import parse_drives
from drivers.odrive import codec
from drivers.odrive.codec import AxisError, AxisState, Cmd, ControlMode, InputMode
from drivers.odrive.host import Intent, OdriveDriver

ROOT = Path(__file__).resolve().parents[2]
DBC = cantools.database.load_file(ROOT / "config" / "can" / "odrive_cansimple.dbc")
REFERENCE = cantools.database.load_file(ROOT / "tests" / "data" / "odrive-cansimple-0.6.10.dbc")
_HEARTBEAT = REFERENCE.get_message_by_name("Axis0_Heartbeat")
REFERENCE_STATES = _HEARTBEAT.get_signal_by_name("Axis_State").choices
REFERENCE_ERRORS = {
    int(k): str(v) for k, v in _HEARTBEAT.get_signal_by_name("Axis_Error").choices.items()
}

NODES = [3, 5, 7, 11, 13, 17, 19, 63]
RADII = [0.05, 0.04, 0.06, 0.05, 0.05, 0.05, 0.05, 0.03]
DIRECTIONS = [1, -1, 1, -1, 1, -1, 1, -1]
OFFSETS = [1.0, 2.0, 0.5, 1.5, 1.0, 1.0, 1.0, 0.25]


def odrive_config(**extra: object):
    return parse_drives(
        {
            "protocol": "odrive",
            "nodes": NODES,
            "gear_ratio": 5.0,
            "direction": DIRECTIONS,
            "length_offset": OFFSETS,
            **extra,
        }
    )


def make_driver(**extra: object) -> OdriveDriver:
    cfg = odrive_config(**extra)
    return OdriveDriver(cfg, cfg.scalings(RADII))


def f32(value: float) -> float:
    return struct.unpack("<f", struct.pack("<f", value))[0]


finite_f32 = st.floats(-1e6, 1e6, allow_nan=False, width=32)
u32 = st.integers(0, 0xFFFFFFFF)
nodes = st.integers(0, codec.NODE_ID_MAX)
ff = st.integers(-32768, 32767).map(lambda k: k * codec.FF_SCALE)


def frame(node: int, cmd: int, data: bytes, **kwargs: object) -> can.Message:
    return can.Message(arbitration_id=node << 5 | cmd, data=data, is_extended_id=False, **kwargs)


def dbc_decode(message: can.Message) -> dict:
    """Decode with cantools by command id (the DBC describes node 0)."""
    return DBC.decode_message(
        message.arbitration_id & codec.CMD_MASK, bytes(message.data), decode_choices=False
    )


def dbc_encode(name: str, signals: dict, node: int) -> can.Message:
    spec = DBC.get_message_by_name(name)
    return frame(node, spec.frame_id, spec.encode(signals))


# -- identifiers and enumerations ------------------------------------------------------


def test_arbitration_id_is_node_shifted_by_five_or_cmd() -> None:
    assert codec.frame_id(3, Cmd.SET_INPUT_TORQUE) == 3 << 5 | 0x0E == 0x6E
    assert codec.frame_id(63, Cmd.CLEAR_ERRORS) == 0x7F8  # still 11 bits
    with pytest.raises(ValueError, match=r"0\.\.63"):
        codec.frame_id(64, Cmd.HEARTBEAT)


def test_command_ids_match_odrive_and_dbc() -> None:
    expected = {
        "Heartbeat": 0x01,
        "Estop": 0x02,
        "Get_Error": 0x03,
        "Set_Axis_State": 0x07,
        "Get_Encoder_Estimates": 0x09,
        "Set_Controller_Mode": 0x0B,
        "Set_Input_Pos": 0x0C,
        "Set_Input_Torque": 0x0E,
        "Clear_Errors": 0x18,
    }
    assert {codec.MESSAGE_NAMES[cmd]: int(cmd) for cmd in Cmd} == expected
    assert {m.name: m.frame_id for m in DBC.messages} == expected


def test_dbc_value_tables_match_the_enums() -> None:
    heartbeat = DBC.get_message_by_name("Heartbeat")
    modes = DBC.get_message_by_name("Set_Controller_Mode")
    tables = [
        (heartbeat.get_signal_by_name("Axis_State"), AxisState),
        (modes.get_signal_by_name("Control_Mode"), ControlMode),
        (modes.get_signal_by_name("Input_Mode"), InputMode),
    ]
    # 15 and 16 came after the 0.6.10 DBC (odrive 0.6.11's enums list them)
    newer = {15: "HARMONIC_CALIBRATION", 16: "HARMONIC_CALIBRATION_COMMUTATION"}
    for signal, enum_type in tables:
        named = {m.value: m.name for m in enum_type}
        if enum_type is AxisState:
            assert {k: named.pop(k) for k in newer} == newer
        assert {int(k): str(v) for k, v in signal.choices.items()} == named


def test_error_bits_are_odrive_0_6() -> None:
    assert AxisError.WATCHDOG_TIMER_EXPIRED == 0x01000000
    assert AxisError.ESTOP_REQUESTED == 0x02000000
    assert AxisError.DC_BUS_OVER_REGEN_CURRENT == 0x800  # 0.5.x's watchdog bit
    text = codec.error_text(0x01000000 | 0x200 | 0x80)
    assert text == "DC_BUS_UNDER_VOLTAGE|WATCHDOG_TIMER_EXPIRED|0x00000080"
    assert codec.error_text(0) == "none"


# -- round trips: codec <-> codec and codec <-> DBC ------------------------------------


@given(nodes, u32, st.sampled_from(list(AxisState)), st.integers(0, 255), st.booleans())
def test_heartbeat_round_trip(node, error, state, result, done) -> None:
    message = codec.encode_heartbeat(node, error, state, result, done)
    assert message.arbitration_id == node << 5 | 1 and len(message.data) == 8
    assert codec.decode_heartbeat(message) == (error, state, result, done)
    assert dbc_decode(message) == {
        "Axis_Error": error,
        "Axis_State": state,
        "Procedure_Result": result,
        "Trajectory_Done_Flag": int(done),
    }
    back = dbc_encode("Heartbeat", dbc_decode(message), node)
    assert codec.decode_heartbeat(back) == (error, state, result, done)


@given(nodes, finite_f32, finite_f32)
def test_encoder_estimates_round_trip(node, pos, vel) -> None:
    message = codec.encode_encoder_estimates(node, pos, vel)
    assert codec.decode_encoder_estimates(message) == (pos, vel)
    assert dbc_decode(message) == {"Pos_Estimate": pos, "Vel_Estimate": vel}
    back = dbc_encode("Get_Encoder_Estimates", {"Pos_Estimate": pos, "Vel_Estimate": vel}, node)
    assert codec.decode_encoder_estimates(back) == (pos, vel)


@given(nodes, u32, u32)
def test_error_status_round_trip(node, active, reason) -> None:
    message = codec.encode_error_status(node, active, reason)
    assert codec.decode_error_status(message) == (active, reason)
    assert dbc_decode(message) == {"Active_Errors": active, "Disarm_Reason": reason}
    back = dbc_encode("Get_Error", {"Active_Errors": active, "Disarm_Reason": reason}, node)
    assert codec.decode_error_status(back) == (active, reason)


@given(nodes, st.sampled_from(list(AxisState)))
def test_set_axis_state_round_trip(node, state) -> None:
    message = codec.encode_set_axis_state(node, state)
    assert message.data == struct.pack("<I", state) + bytes(4)  # 8 bytes, as ODrive's DBC
    assert codec.decode_set_axis_state(message) is state
    assert dbc_decode(message) == {"Axis_Requested_State": state}
    back = dbc_encode("Set_Axis_State", {"Axis_Requested_State": int(state)}, node)
    assert codec.decode_set_axis_state(back) is state


@given(nodes, st.sampled_from(list(ControlMode)), st.sampled_from(list(InputMode)))
def test_set_controller_mode_round_trip(node, control, inputs) -> None:
    message = codec.encode_set_controller_mode(node, control, inputs)
    assert codec.decode_set_controller_mode(message) == (control, inputs)
    assert dbc_decode(message) == {"Control_Mode": control, "Input_Mode": inputs}
    back = dbc_encode("Set_Controller_Mode", {"Control_Mode": control, "Input_Mode": inputs}, node)
    assert codec.decode_set_controller_mode(back) == (control, inputs)


@given(nodes, finite_f32, ff, ff)
def test_set_input_pos_round_trip(node, pos, vel_ff, torque_ff) -> None:
    message = codec.encode_set_input_pos(node, pos, vel_ff, torque_ff)
    decoded = codec.decode_set_input_pos(message)
    assert decoded[0] == pos
    assert decoded[1:] == pytest.approx((vel_ff, torque_ff), abs=1e-9)
    by_dbc = dbc_decode(message)
    assert by_dbc["Input_Pos"] == pos
    assert (by_dbc["Vel_FF"], by_dbc["Torque_FF"]) == pytest.approx((vel_ff, torque_ff), abs=1e-9)
    back = dbc_encode("Set_Input_Pos", by_dbc, node)
    assert back.data == message.data


@given(nodes, finite_f32)
def test_set_input_torque_round_trip(node, torque) -> None:
    message = codec.encode_set_input_torque(node, torque)
    assert message.data == struct.pack("<f", torque) + bytes(4)  # 8 bytes, as ODrive's DBC
    assert codec.decode_set_input_torque(message) == torque
    assert dbc_decode(message) == {"Input_Torque": torque}
    back = dbc_encode("Set_Input_Torque", {"Input_Torque": torque}, node)
    assert codec.decode_set_input_torque(back) == torque


@given(nodes, st.booleans())
def test_clear_errors_and_estop_round_trip(node, identify) -> None:
    message = codec.encode_clear_errors(node, identify)
    assert codec.decode_clear_errors(message) is identify
    assert dbc_decode(message) == {"Identify": int(identify)}
    assert codec.decode_clear_errors(dbc_encode("Clear_Errors", {"Identify": identify}, node)) is (
        identify
    )
    estop = codec.encode_estop(node)
    assert estop.arbitration_id == node << 5 | 2 and len(estop.data) == 0
    assert dbc_decode(estop) == {}


def test_requests_are_remote_frames() -> None:
    request = codec.encode_request(4, Cmd.GET_ERROR)
    assert request.is_remote_frame and not request.is_extended_id
    assert request.arbitration_id == 4 << 5 | 3
    assert codec.is_error_request(request)
    assert codec.is_error_request(frame(4, 3, b""))
    assert codec.is_error_request(frame(4, 3, b"\x00"))
    assert not codec.is_error_request(frame(4, 3, bytes(8)))


def test_encoders_refuse_what_cannot_be_sent() -> None:
    for bad in (math.nan, math.inf, -math.inf, 1e39):
        with pytest.raises(FrameError, match="float32"):
            codec.encode_set_input_torque(1, bad)
        with pytest.raises(FrameError, match="float32"):
            codec.encode_encoder_estimates(1, bad, 0.0)
    with pytest.raises(FrameError, match="torque_ff"):
        codec.encode_set_input_pos(1, 0.0, 0.0, 40.0)
    with pytest.raises(FrameError, match="vel_ff"):
        codec.encode_set_input_pos(1, 0.0, math.nan, 0.0)


# -- every decoder on hostile bytes ------------------------------------------------------

DECODERS = [
    (Cmd.HEARTBEAT, codec.decode_heartbeat),
    (Cmd.GET_ENCODER_ESTIMATES, codec.decode_encoder_estimates),
    (Cmd.GET_ERROR, codec.decode_error_status),
    (Cmd.SET_AXIS_STATE, codec.decode_set_axis_state),
    (Cmd.SET_CONTROLLER_MODE, codec.decode_set_controller_mode),
    (Cmd.SET_INPUT_POS, codec.decode_set_input_pos),
    (Cmd.SET_INPUT_TORQUE, codec.decode_set_input_torque),
    (Cmd.CLEAR_ERRORS, codec.decode_clear_errors),
]


@pytest.mark.parametrize(("cmd", "decode"), DECODERS, ids=[c.name for c, _ in DECODERS])
@given(data=st.binary(max_size=12))
def test_decoders_return_valid_values_or_raise_frame_error(cmd, decode, data) -> None:
    message = frame(9, cmd, data, is_fd=len(data) > 8)
    try:
        value = decode(message)
    except codec.OdriveFrameError as exc:
        assert exc.reason.startswith(codec.MESSAGE_NAMES[cmd] + ".")
        assert f"0x{message.arbitration_id:03X}" in str(exc)
        return
    assert len(data) <= 8
    values = value if isinstance(value, tuple) else (value,)
    assert all(math.isfinite(v) for v in values if isinstance(v, float))


@pytest.mark.parametrize(
    ("message", "decode", "reason"),
    [
        (frame(1, 1, bytes(6)), codec.decode_heartbeat, "Heartbeat.dlc"),
        (frame(1, 1, bytes(7)), codec.decode_heartbeat, "Heartbeat.dlc"),
        (frame(1, 9, bytes(7)), codec.decode_encoder_estimates, "Get_Encoder_Estimates.dlc"),
        (
            frame(1, 9, struct.pack("<ff", math.nan, 0.0)),
            codec.decode_encoder_estimates,
            "Get_Encoder_Estimates.non_finite",
        ),
        (
            frame(1, 7, struct.pack("<I4x", 17)),
            codec.decode_set_axis_state,
            "Set_Axis_State.axis_state",
        ),
        (
            frame(1, 7, struct.pack("<I4x", 1 << 20)),
            codec.decode_set_axis_state,
            "Set_Axis_State.axis_state",
        ),
        (frame(1, 7, struct.pack("<I", 8)), codec.decode_set_axis_state, "Set_Axis_State.dlc"),
        (
            frame(1, 11, struct.pack("<II", 4, 1)),
            codec.decode_set_controller_mode,
            "Set_Controller_Mode.control_mode",
        ),
        (
            frame(1, 11, struct.pack("<II", 1, 9)),
            codec.decode_set_controller_mode,
            "Set_Controller_Mode.input_mode",
        ),
        (
            frame(1, 14, struct.pack("<f4x", math.inf)),
            codec.decode_set_input_torque,
            "Set_Input_Torque.non_finite",
        ),
        (
            frame(1, 14, struct.pack("<f", 1.0)),
            codec.decode_set_input_torque,
            "Set_Input_Torque.dlc",
        ),
        (frame(1, 24, b""), codec.decode_clear_errors, "Clear_Errors.dlc"),
        (
            frame(1, 12, struct.pack("<fhh", -math.inf, 0, 0)),
            codec.decode_set_input_pos,
            "Set_Input_Pos.non_finite",
        ),
    ],
)
def test_malformed_frames_name_their_problem(message, decode, reason) -> None:
    with pytest.raises(codec.OdriveFrameError) as info:
        decode(message)
    assert info.value.reason == reason


def test_longer_frames_are_accepted_like_the_firmware_does() -> None:
    padded = frame(2, Cmd.CLEAR_ERRORS, b"\x01" + bytes(7))
    assert codec.decode_clear_errors(padded) is True


@pytest.mark.parametrize("state", range(17))
def test_every_axis_state_of_firmware_0_6_is_decoded_and_named(state: int) -> None:
    data = struct.pack("<IBBBx", 0, state, 0, 0)
    heartbeat = codec.decode_heartbeat(frame(1, Cmd.HEARTBEAT, data))
    assert isinstance(heartbeat.axis_state, AxisState) and heartbeat.axis_state == state
    name = {15: "HARMONIC_CALIBRATION", 16: "HARMONIC_CALIBRATION_COMMUTATION"}.get(state)
    assert heartbeat.axis_state.name == (name or str(REFERENCE_STATES[state]))


def test_an_unlisted_axis_state_is_decoded_not_dropped() -> None:
    heartbeat = codec.decode_heartbeat(frame(1, 1, struct.pack("<IBBBx", 0, 42, 0, 1)))
    assert heartbeat == (0, 42, 0, True)
    assert not isinstance(heartbeat.axis_state, AxisState)


def test_every_error_bit_of_firmware_0_6_is_named() -> None:
    assert AxisError.REQUESTED_CURRENT_TOO_HIGH == 0x20000  # odrive 0.6.11's enums
    for bit, name in REFERENCE_ERRORS.items():
        if bit:
            assert AxisError(bit).name == name
    assert codec.error_text(0x20000 | 0x80000000) == "REQUESTED_CURRENT_TOO_HIGH|0x80000000"


# -- host: scaling and sign conventions --------------------------------------------------


def test_driver_construction() -> None:
    driver = make_driver()
    assert driver.timing is Timing.CYCLIC
    assert driver.nodes == NODES and driver.n == 8
    assert driver.cycle_start() == []
    assert driver.feed_period == pytest.approx(0.05 / 3)
    assert driver.timeout == pytest.approx(1.05)  # 3 heartbeat timeouts
    cia402 = parse_drives({"protocol": "cia402", "nodes": [1], "rated_torque": 1.0})
    with pytest.raises(ValueError, match="protocol odrive"):
        OdriveDriver(cia402, [Scaling(0.05)])
    one = parse_drives({"protocol": "odrive", "nodes": [1]})
    with pytest.raises(ValueError, match="counts_per_rev must be 1"):
        OdriveDriver(one, [Scaling(0.05, counts_per_rev=8192)])
    with pytest.raises(ValueError, match="2 scalings for 1"):
        OdriveDriver(one, [Scaling(0.05), Scaling(0.05)])


def test_holding_brake_needs_a_brake_in_the_config() -> None:
    with pytest.raises(ConfigError, match="has_holding_brake"):
        odrive_config(brake="holding_brake")
    driver = make_driver(brake="holding_brake", has_holding_brake=True)
    assert driver.has_holding_brake


def test_commands_convert_forces_to_motor_torque_with_sign() -> None:
    driver = make_driver()
    forces = [-100.0, -50.0, 10.0, 0.0, -1.0, 2.5, -300.0, 7.0]
    frames = driver.commands(forces)
    assert len(frames) == 8
    for i, (message, force) in enumerate(zip(frames, forces, strict=True)):
        assert message.arbitration_id == NODES[i] << 5 | Cmd.SET_INPUT_TORQUE
        assert not message.is_extended_id and message.data[4:] == bytes(4)  # 8 bytes, DBC
        torque = codec.decode_set_input_torque(message)
        expected = DIRECTIONS[i] * force * RADII[i] / 5.0
        assert torque == pytest.approx(expected, rel=1e-6)
        assert dbc_decode(message)["Input_Torque"] == torque
        # A tension (f < 0) with direction +1 is a negative motor torque.
        assert math.copysign(1, torque) == math.copysign(1, DIRECTIONS[i] * force) or force == 0


def test_commands_refuse_non_finite_forces_naming_the_actuator() -> None:
    driver = make_driver()
    forces = [0.0] * 8
    for bad in (math.nan, math.inf, -1e45):
        forces[5] = bad
        with pytest.raises(FrameError, match=r"actuator 5 .*node 17"):
            driver.commands(forces)
    with pytest.raises(ValueError, match="3 forces"):
        driver.commands([0.0] * 3)


def test_estimates_become_lengths_and_rates() -> None:
    driver = make_driver()
    for i, node in enumerate(NODES):
        message = codec.encode_encoder_estimates(node, 2.5, -0.5)
        assert driver.receive(message, now=10.0 + i) == i
        feedback = driver.feedback[i]
        metres_per_turn = DIRECTIONS[i] * 2 * math.pi * RADII[i] / 5.0
        assert feedback.length == pytest.approx(OFFSETS[i] + 2.5 * metres_per_turn)
        assert feedback.rate == pytest.approx(-0.5 * metres_per_turn)
        assert feedback.stamp == 10.0 + i and feedback.count == 1
    assert driver.receive(codec.encode_encoder_estimates(NODES[0], 0.0, 0.0), 20.0) == 0
    assert driver.feedback[0].count == 2
    assert driver.feedback[0].length == pytest.approx(OFFSETS[0])
    assert driver.counters.accepted == 9 and driver.counters.rejected_total == 0


@pytest.mark.parametrize("turns", [-1000.0, -1.0, 0.0, 0.25, 3.0])
def test_estimate_and_hold_position_agree(turns: float) -> None:
    """The length a drive reports at `turns` is the length a hold there asks for."""
    driver = make_driver()
    driver.receive(codec.encode_encoder_estimates(NODES[1], turns, 0.0), 0.0)
    length = driver.feedback[1].length
    lengths = [math.nan] * 8
    lengths[1] = length
    hold = driver.brake(lengths, BrakeMode.POSITION_HOLD)
    pos_frames = [m for m in hold if m.arbitration_id == NODES[1] << 5 | Cmd.SET_INPUT_POS]
    assert codec.decode_set_input_pos(pos_frames[0])[0] == pytest.approx(f32(turns))
    assert driver.scalings[1].position(length) == pytest.approx(turns, abs=1e-9)


def test_heartbeats_set_status_and_name_error_bits() -> None:
    driver = make_driver()
    assert driver.status[2].state is DriveState.UNKNOWN
    driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.IDLE), 1.0)
    assert driver.status[2].state is DriveState.READY
    assert driver.status[2].heartbeat_stamp == 1.0 and driver.status[2].fault is None
    driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.CLOSED_LOOP_CONTROL), 1.1)
    assert driver.status[2].state is DriveState.ENABLED
    driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.MOTOR_CALIBRATION), 1.2)
    assert driver.status[2].state is DriveState.DISABLED
    error = AxisError.WATCHDOG_TIMER_EXPIRED | AxisError.DC_BUS_UNDER_VOLTAGE
    driver.receive(codec.encode_heartbeat(NODES[2], error, AxisState.CLOSED_LOOP_CONTROL), 1.3)
    status = driver.status[2]
    assert status.state is DriveState.FAULT and status.fault_code == error
    assert "node 7" in status.fault
    assert "WATCHDOG_TIMER_EXPIRED" in status.fault and "DC_BUS_UNDER_VOLTAGE" in status.fault
    driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.CLOSED_LOOP_CONTROL), 1.4)
    assert driver.status[2].state is DriveState.ENABLED and driver.status[2].fault is None
    assert driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.IDLE), 1.5) is None


def test_get_error_answers_are_stored() -> None:
    driver = make_driver()
    requests = driver.request_errors()
    assert [m.arbitration_id for m in requests] == [n << 5 | 3 for n in NODES]
    assert all(m.is_remote_frame for m in requests)
    driver.receive(codec.encode_error_status(NODES[4], 0x01000000, 0x01000000), 0.0)
    assert driver.drive_errors[4] == (0x01000000, 0x01000000)
    driver.receive(frame(NODES[4], 3, b""), 0.0)  # another host's request
    assert driver.drive_errors[4] == (0x01000000, 0x01000000) and driver.ignored == 1


# -- host: brakes, keepalive, disable ------------------------------------------------------


def decoded(frames: list[can.Message]) -> list[tuple[int, Cmd, object]]:
    out = []
    for m in frames:
        cmd = Cmd(m.arbitration_id & 0x1F)
        value = {
            Cmd.SET_AXIS_STATE: codec.decode_set_axis_state,
            Cmd.SET_CONTROLLER_MODE: codec.decode_set_controller_mode,
            Cmd.SET_INPUT_POS: codec.decode_set_input_pos,
        }[cmd](m)
        out.append((m.arbitration_id >> 5, cmd, value))
    return out


def test_position_hold_brake_servoes_every_cable_at_its_length() -> None:
    driver = make_driver()
    lengths = [1.1, 2.2, 0.7, 1.4, 1.3, 0.9, 1.05, 0.3]
    frames = driver.brake(lengths, BrakeMode.POSITION_HOLD)
    items = decoded(frames)
    assert len(items) == 24
    for i, node in enumerate(NODES):
        mode, state, pos = items[3 * i : 3 * i + 3]
        assert mode == (
            node,
            Cmd.SET_CONTROLLER_MODE,
            (ControlMode.POSITION_CONTROL, InputMode.PASSTHROUGH),
        )
        assert state == (node, Cmd.SET_AXIS_STATE, AxisState.CLOSED_LOOP_CONTROL)
        turns = driver.scalings[i].position(lengths[i])
        assert pos[:2] == (node, Cmd.SET_INPUT_POS)
        assert pos[2] == pytest.approx((turns, 0.0, 0.0), rel=1e-6)
    assert driver.intent == [Intent.HOLD_POSITION] * 8
    clock = [0.0]
    driver._now = lambda: clock[0]  # as start() leaves it
    # once per feed period the position mode again (firmware 0.6 reports no control
    # mode: another node may have changed it), then the hold
    keep = driver.keepalive()
    no_state = [m.data for m in frames if m.arbitration_id & 0x1F != Cmd.SET_AXIS_STATE]
    assert [m.data for m in keep] == no_state
    clock[0] += driver.feed_period / 2
    keep = driver.keepalive()
    assert [m.data for m in keep] == [m.data for m in frames[2::3]]
    assert all(m.arbitration_id & 0x1F == Cmd.SET_INPUT_POS for m in keep)
    assert not any(m.arbitration_id & 0x1F == Cmd.ESTOP for m in frames + keep)


def test_holding_brake_is_idle_only_with_a_brake() -> None:
    lengths = [1.0] * 8
    with_brake = make_driver(has_holding_brake=True, brake="holding_brake")
    items = decoded(with_brake.brake(lengths, BrakeMode.HOLDING_BRAKE))
    assert items == [(node, Cmd.SET_AXIS_STATE, AxisState.IDLE) for node in NODES]
    assert requests(with_brake.keepalive()) == NODES  # IDLE: the watchdog counts too
    with_brake.receive(codec.encode_heartbeat(NODES[0], 0, AxisState.IDLE), 0.0)
    assert with_brake.status[0].state is DriveState.HOLDING
    # Asked for the holding brake without one: position hold, never IDLE.
    without = make_driver()
    items = decoded(without.brake(lengths, BrakeMode.HOLDING_BRAKE))
    assert AxisState.IDLE not in [value for _, _, value in items]
    assert [cmd for _, cmd, _ in items[:3]] == [
        Cmd.SET_CONTROLLER_MODE,
        Cmd.SET_AXIS_STATE,
        Cmd.SET_INPUT_POS,
    ]
    without.receive(codec.encode_heartbeat(NODES[0], 0, AxisState.IDLE), 0.0)
    assert without.status[0].state is DriveState.READY  # IDLE without a brake holds nothing


def test_brake_without_a_length_holds_at_the_drives_own_estimate() -> None:
    """No trusted length: the mode change alone holds at the drive's own estimate, never
    at a length a frame reported (it may be forged)."""
    driver = make_driver()
    driver.receive(codec.encode_encoder_estimates(NODES[0], 4.0, 0.0), 0.0)
    frames = driver.brake([math.nan] * 8, BrakeMode.POSITION_HOLD)
    items = decoded(frames)
    for node in NODES[:2]:  # node 0 reported 4.0 turns, node 5 was never heard
        assert [cmd for n, cmd, _ in items if n == node] == [
            Cmd.SET_CONTROLLER_MODE,
            Cmd.SET_AXIS_STATE,
        ]
    keep = decoded(driver.keepalive())
    assert keep[:2] == [
        (node, Cmd.SET_CONTROLLER_MODE, (ControlMode.POSITION_CONTROL, InputMode.PASSTHROUGH))
        for node in NODES[:2]
    ]


def test_disable_idles_every_axis() -> None:
    driver = make_driver()
    assert decoded(driver.disable()) == [(n, Cmd.SET_AXIS_STATE, AxisState.IDLE) for n in NODES]
    assert requests(driver.keepalive()) == NODES  # feeds the idle axes' watchdogs
    assert driver.disable() == []  # asked for IDLE already


def requests(frames: list[can.Message]) -> list[int]:
    """The nodes `frames` send a Get_Error request (RTR) to, each frame being one."""
    assert all(m.is_remote_frame and m.arbitration_id & 0x1F == Cmd.GET_ERROR for m in frames)
    return [m.arbitration_id >> 5 for m in frames]


def heartbeats(driver: OdriveDriver, state: AxisState) -> None:
    for node in NODES:
        driver.receive(codec.encode_heartbeat(node, 0, state), 0.0)


def commanded_states(frames: list[can.Message]) -> list[AxisState]:
    return [value for _, cmd, value in decoded(frames) if cmd is Cmd.SET_AXIS_STATE]


@pytest.mark.parametrize("mode", list(BrakeMode))
def test_brake_never_restarts_an_axis_in_closed_loop(mode: BrakeMode) -> None:
    """Firmware restarts an axis asked for CLOSED_LOOP_CONTROL while in it (a torque gap
    at the moment of braking): the brake of a torque-controlled axis only changes mode."""
    driver = make_driver()
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)
    frames = driver.brake([1.0] * 8, mode)
    assert commanded_states(frames) == []
    assert [cmd for _, cmd, _ in decoded(frames)] == [
        Cmd.SET_CONTROLLER_MODE,
        Cmd.SET_INPUT_POS,
    ] * 8


def test_axis_state_is_requested_once_until_a_heartbeat_says_otherwise() -> None:
    driver = make_driver()
    heartbeats(driver, AxisState.IDLE)
    assert (
        commanded_states(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD))
        == [AxisState.CLOSED_LOOP_CONTROL] * 8
    )
    assert commanded_states(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD)) == []
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)  # reached
    assert commanded_states(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD)) == []
    heartbeats(driver, AxisState.IDLE)  # dropped out (an axis error, on firmware 0.6)
    assert (
        commanded_states(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD))
        == [AxisState.CLOSED_LOOP_CONTROL] * 8
    )
    assert commanded_states(driver.disable()) == [AxisState.IDLE] * 8  # asked since
    heartbeats(driver, AxisState.IDLE)
    assert commanded_states(driver.disable()) == []


def test_a_braked_idle_axis_stays_braked_whatever_brake_mode() -> None:
    """Its brake holds already: releasing it into a position loop would let the load sag."""
    driver = make_driver(has_holding_brake=True)
    heartbeats(driver, AxisState.IDLE)
    assert driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD) == []
    assert driver.intent == [Intent.HOLD_BRAKE] * 8
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)  # armed: held by position control
    assert Cmd.SET_INPUT_POS in [
        cmd for _, cmd, _ in decoded(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD))
    ]


def test_position_hold_feeds_the_last_torque_forward() -> None:
    """Firmware 0.6 takes Set_Input_Pos' torque_ff as input_torque, the position loop's
    feed-forward: the hold after torque control keeps carrying the load (0 would drop it
    onto the position loop)."""
    driver = make_driver()
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)
    forces = [-100.0, -50.0, 10.0, 0.0, -1.0, 2.5, -300.0, 7.0]
    driver.commands(forces)
    holds = [
        v
        for _, cmd, v in decoded(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD))
        if cmd is Cmd.SET_INPUT_POS
    ]
    for i, (_pos, _vel_ff, torque_ff) in enumerate(holds):
        assert torque_ff == pytest.approx(driver.scalings[i].motor_torque(forces[i]), abs=6e-4)
    # a keepalive due to feed (no clock: always) asks for position control again too
    assert [m.data for m in driver.keepalive()] == [
        m.data for m in driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD)
    ]
    driver.disable()
    heartbeats(driver, AxisState.IDLE)
    assert all(
        v[2] == 0.0
        for _, cmd, v in decoded(driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD))
        if cmd is Cmd.SET_INPUT_POS
    )  # disarmed: nothing carried any more


def test_keepalive_feeds_idle_axes_once_per_feed_period() -> None:
    """Firmware 0.6 counts the watchdog in IDLE too and any frame feeds it: idle axes get
    a Get_Error request (RTR) every third of watchdog_timeout, holding ones Set_Input_Pos
    every call, torque-controlled ones nothing."""
    driver = make_driver()
    clock = [0.0]
    driver._now = lambda: clock[0]  # as start() leaves it
    driver.disable()
    driver.intent[1] = Intent.TORQUE
    assert requests(driver.keepalive()) == [n for i, n in enumerate(NODES) if i != 1]
    clock[0] += driver.feed_period * 0.9
    assert driver.keepalive() == []
    clock[0] += driver.feed_period * 0.2
    assert len(driver.keepalive()) == 7


def test_an_unlisted_axis_state_is_a_named_fault() -> None:
    driver = make_driver()
    driver.receive(frame(NODES[2], Cmd.HEARTBEAT, struct.pack("<IBBBx", 0, 42, 0, 1)), 1.0)
    status = driver.status[2]
    assert status.state is DriveState.FAULT
    assert status.fault == f"ODrive node {NODES[2]}: unknown axis state 42 (not in firmware 0.6)"
    assert status.heartbeat_stamp == 1.0  # heard, not a silent axis
    assert driver.counters.rejected == {}
    driver.receive(codec.encode_heartbeat(NODES[2], 0, AxisState.HARMONIC_CALIBRATION), 2.0)
    assert status.state is DriveState.DISABLED and status.fault is None


# -- host: hostile input --------------------------------------------------------------------


def test_hostile_frames_are_counted_and_never_acted_on() -> None:
    driver = make_driver()
    driver.receive(codec.encode_encoder_estimates(NODES[0], 1.0, 0.0), 0.0)
    driver.receive(codec.encode_heartbeat(NODES[0], 0, AxisState.IDLE), 0.0)
    before = (driver.feedback[0].length, driver.feedback[0].count, driver.status[0].state)
    hostile = [
        frame(NODES[0], 9, bytes(4)),  # short estimate
        frame(NODES[0], 9, struct.pack("<ff", math.nan, 0.0)),
        frame(NODES[0], 9, struct.pack("<ff", 0.0, -math.inf)),
        frame(NODES[0], 1, bytes(3)),  # short heartbeat
        frame(NODES[0], 1, bytes(7)),  # the DBC's heartbeat has 8 bytes
        frame(NODES[0], 3, bytes(5)),  # Get_Error answer of the wrong length
        frame(NODES[0], 9, bytes(12), is_fd=True),
    ]
    for message in hostile:
        assert driver.receive(message, 1.0) is None
    assert driver.counters.rejected == {
        "Get_Encoder_Estimates.dlc": 2,
        "Get_Encoder_Estimates.non_finite": 2,
        "Heartbeat.dlc": 2,
        "Get_Error.dlc": 1,
    }
    ignored = [
        frame(40, 9, bytes(8)),  # unknown node
        frame(NODES[0], 0x0E, bytes(4)),  # a command, not a reply
        frame(NODES[0], 0x1F, bytes(8)),  # unknown command
        can.Message(arbitration_id=NODES[0] << 5 | 9, data=bytes(8), is_extended_id=True),
        can.Message(arbitration_id=NODES[0] << 5 | 9, is_remote_frame=True, is_extended_id=False),
        can.Message(is_error_frame=True),
    ]
    for message in ignored:
        assert driver.receive(message, 1.0) is None
    assert driver.ignored == len(ignored)
    assert (driver.feedback[0].length, driver.feedback[0].count, driver.status[0].state) == before
    assert driver.counters.accepted == 2


@given(
    st.lists(
        st.tuples(
            st.integers(0, 0x7FF),
            st.binary(max_size=8),
            st.booleans(),
            st.booleans(),
        ),
        max_size=50,
    )
)
def test_receive_never_raises(frames) -> None:
    driver = make_driver()
    for arbitration_id, data, extended, remote in frames:
        message = can.Message(
            arbitration_id=arbitration_id,
            data=b"" if remote else data,
            is_extended_id=extended,
            is_remote_frame=remote,
        )
        index = driver.receive(message, 0.0)
        assert index is None or driver.feedback[index].count > 0
    for feedback in driver.feedback:
        assert feedback.count == 0 or math.isfinite(feedback.length)
    total = driver.counters.accepted + driver.counters.rejected_total + driver.ignored
    assert total == len(frames)


def test_flood_of_malformed_frames() -> None:
    driver = make_driver()
    bad = [frame(node, 9, struct.pack("<ff", math.nan, 1.0)) for node in NODES]
    for _ in range(2000):
        for message in bad:
            driver.receive(message, 0.0)
    assert driver.counters.rejected["Get_Encoder_Estimates.non_finite"] == 16000
    assert all(f.count == 0 and math.isnan(f.length) for f in driver.feedback)


def test_a_hold_is_confirmed_by_heartbeat_and_an_axis_moved_by_another_node_is_asked_back() -> None:
    """Position hold: confirmed by a heartbeat in closed loop; another node's IDLE makes it
    unconfirmed (no brake) and the host asks for closed loop again.  Holding brake: IDLE
    confirms; another node's closed loop is undone by asking for IDLE again."""
    driver = make_driver()
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)
    driver.brake([1.0] * 8, BrakeMode.POSITION_HOLD)
    assert [s.held for s in driver.status] == [None] * 8  # asked, not yet seen
    heartbeats(driver, AxisState.CLOSED_LOOP_CONTROL)
    assert [s.held for s in driver.status] == [True] * 8
    driver.receive(codec.encode_heartbeat(NODES[3], 0, AxisState.IDLE), 1.0)
    assert driver.status[3].held is False
    assert f"ODrive node {NODES[3]}: IDLE, not its hold" in driver.status[3].hold_problem
    asked = decoded(driver.keepalive())
    assert (NODES[3], Cmd.SET_AXIS_STATE, AxisState.CLOSED_LOOP_CONTROL) in asked
    assert sum(cmd is Cmd.SET_AXIS_STATE for _, cmd, _ in asked) == 1

    braked = make_driver(has_holding_brake=True, brake="holding_brake")
    heartbeats(braked, AxisState.IDLE)
    braked.brake([1.0] * 8, BrakeMode.HOLDING_BRAKE)
    heartbeats(braked, AxisState.IDLE)
    assert [s.held for s in braked.status] == [True] * 8
    braked.receive(codec.encode_heartbeat(NODES[5], 0, AxisState.CLOSED_LOOP_CONTROL), 1.0)
    assert braked.status[5].held is False
    asked = [m for m in braked.keepalive() if not m.is_remote_frame]  # watchdog feeds aside
    assert decoded(asked) == [(NODES[5], Cmd.SET_AXIS_STATE, AxisState.IDLE)]
