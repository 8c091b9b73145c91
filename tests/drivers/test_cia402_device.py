"""The simulated CiA 402 drive on its own: NMT, SDO server, the 402 state machine driven by
RPDOs and SDO, the RPDO deadline, brake reactions, torque scaling, and hostile frames
(host <-> device round trips: tests/drivers/test_cia402.py)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.base import Actuation, BrakeMode
from drivers.cia402 import codec
from drivers.cia402.codec import EDS_PATH, NmtCommand, NmtState, SdoKind
from drivers.cia402.statemachine import (
    CONTROL_RELEASE_HOLD,
    MODE_CSP,
    MODE_CST,
    STATUS_HOLD,
    Command,
    State,
    decode_statusword,
)
from drivers.config import parse_drives
from sim_bus.devices.cia402 import Cia402Drive

NODE = 5
RADIUS = 0.04


def configure(device: Cia402Drive) -> None:
    """What a master writes (CiA 301 procedure): the default profile's PDO mapping, RPDO
    deadline 100 ms, quick stop option 6 (hold)."""
    for layout in codec.PDO_LAYOUTS:
        for index, sub, value in layout.mapping_procedure(NODE):
            size = 1 if (index, sub) in ((layout.comm_index, 2), (layout.map_index, 0)) else 4
            assert sdo_write(device, index, sub, value.to_bytes(size, "little")).kind is (
                SdoKind.DOWNLOAD
            )
    assert sdo_write(device, 0x1400, 5, (100).to_bytes(2, "little")).kind is SdoKind.DOWNLOAD
    assert sdo_write(device, 0x1401, 5, (100).to_bytes(2, "little")).kind is SdoKind.DOWNLOAD
    assert sdo_write(device, 0x605A, 0, (6).to_bytes(2, "little")).kind is SdoKind.DOWNLOAD


def drive(**overrides) -> Cia402Drive:
    """A drive at 2.0 m, booted, configured (`configure`) and operational, heartbeat off."""
    power_on_hold = overrides.pop("power_on_hold", False)
    mapped = overrides.pop("mapped", True)
    data = {
        "protocol": "cia402",
        "nodes": [NODE],
        "rated_torque": 1.5,
        "gear_ratio": 8.0,
        "counts_per_rev": 1 << 17,
        "direction": -1,
        "length_offset": 3.0,
    }
    data.update(overrides)
    config = parse_drives(data)
    device = Cia402Drive(NODE, config.scalings([RADIUS])[0], config, power_on_hold=power_on_hold)
    device.measure(2.0, 0.0)
    device.on_tick(0.0)
    if mapped:
        configure(device)
    device.on_frame(codec.encode_nmt(NmtCommand.START, NODE), 0.0)
    return device


def frames_of(frames: list[can.Message]) -> list[tuple[int, bytes]]:
    return [(f.arbitration_id, bytes(f.data)) for f in frames]


BOOT_UP = [(0x700 + NODE, b"\x00")]


def send(device: Cia402Drive, frame: can.Message, now: float = 0.0) -> list[can.Message]:
    return device.on_frame(frame, now)


def sdo_read(device: Cia402Drive, index: int, sub: int = 0) -> codec.Sdo:
    (answer,) = send(device, codec.encode_sdo_upload_request(NODE, index, sub))
    assert answer.arbitration_id == 0x580 + NODE
    return codec.decode_sdo_response(answer.arbitration_id, answer.data)


def sdo_write(
    device: Cia402Drive, index: int, sub: int, data: bytes, now: float = 0.0
) -> codec.Sdo:
    frames = send(device, codec.encode_sdo_download_request(NODE, index, sub, data), now)
    return codec.decode_sdo_response(frames[0].arbitration_id, frames[0].data)


def rpdo1(device: Cia402Drive, word: int, torque: int = 0, now: float = 0.0, mode: int = MODE_CST):
    return send(device, codec.encode_rpdo1(NODE, word, torque, mode), now)


def rpdo2(device: Cia402Drive, word: int, position: int, now: float = 0.0, mode: int = MODE_CSP):
    return send(device, codec.encode_rpdo2(NODE, word, position, mode), now)


def enable(device: Cia402Drive, now: float = 0.0) -> None:
    for word in (0x06, 0x07, 0x0F):
        rpdo1(device, word, 0, now)
    assert device.state is State.OPERATION_ENABLED


def emcy_codes(frames: list[can.Message]) -> list[int]:
    return [
        codec.decode_emcy(f.arbitration_id, f.data)[0]
        for f in frames
        if f.arbitration_id == 0x80 + NODE
    ]


# -- NMT and heartbeat ---------------------------------------------------------------------


def test_boot_up_then_heartbeats_at_the_configured_period() -> None:
    config = parse_drives({"protocol": "cia402", "nodes": [NODE], "rated_torque": 1.0})
    device = Cia402Drive(NODE, config.scalings([RADIUS])[0], config)
    assert device.on_frame(codec.encode_nmt(NmtCommand.START, 0), 0.0) == []  # not booted
    assert frames_of(device.on_tick(0.0)) == BOOT_UP
    assert device.nmt_state is NmtState.PRE_OPERATIONAL and device.state is State.SWITCH_ON_DISABLED
    assert device.on_tick(1.0) == []  # 0x1017 = 0: no heartbeat
    assert sdo_write(device, 0x1017, 0, struct.pack("<H", 20), 1.0).kind is SdoKind.DOWNLOAD
    beats = [f for k in range(1, 101) for f in device.on_tick(1.0 + k * 0.001)]
    assert frames_of(beats) == [(0x700 + NODE, b"\x7f")] * 5


def test_nmt_commands_and_their_effects() -> None:
    device = drive()
    assert device.nmt_state is NmtState.OPERATIONAL
    send(device, codec.encode_nmt(NmtCommand.STOP, NODE + 1))  # another node
    assert device.nmt_state is NmtState.OPERATIONAL
    send(device, codec.encode_nmt(NmtCommand.STOP, 0))  # every node
    assert device.nmt_state is NmtState.STOPPED
    assert send(device, codec.encode_sdo_upload_request(NODE, 0x1000, 0)) == []
    assert device.counters.rejected["SDO while stopped"] == 1
    send(device, codec.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE))
    assert send(device, codec.encode_sync()) == []  # no PDOs in pre-operational
    assert rpdo1(device, 0x06) == [] and device.state is State.SWITCH_ON_DISABLED
    assert device.counters.rejected["RPDO outside OPERATIONAL"] == 1
    assert sdo_read(device, 0x1000).data == struct.pack("<L", 0x00020192)
    sdo_write(device, 0x1017, 0, struct.pack("<H", 100))
    reset = send(device, codec.encode_nmt(NmtCommand.RESET_COMMUNICATION, NODE))
    assert frames_of(reset) == BOOT_UP
    assert device.heartbeat_period == 0.0 and device.nmt_state is NmtState.PRE_OPERATIONAL


def test_reset_node_restores_the_eds_but_keeps_stored_parameters() -> None:
    device = drive(brake="holding_brake", has_holding_brake=True)
    sdo_write(device, 0x6072, 0, struct.pack("<H", 1200))
    enable(device)
    assert frames_of(send(device, codec.encode_nmt(NmtCommand.RESET_NODE, 0))) == BOOT_UP
    assert device.state is State.SWITCH_ON_DISABLED and device.max_torque == 3000
    assert device.actuation is Actuation.OFF and device.brake_engaged
    assert sdo_read(device, 0x6076).data == struct.pack("<L", 1500)
    assert device.brake_reaction is BrakeMode.HOLDING_BRAKE


# -- SDO server ------------------------------------------------------------------------------


def test_sdo_uploads_give_eds_values_and_live_objects() -> None:
    device = drive()
    assert sdo_read(device, 0x1018, 2).data == struct.pack("<L", 0x402)
    assert sdo_read(device, 0x1400, 1).data == struct.pack("<L", 0x200 + NODE)
    assert sdo_read(device, 0x1A00, 2).data == struct.pack("<L", 0x60640020)
    assert sdo_read(device, 0x605A).data == struct.pack("<h", 6)  # configure() wrote it
    assert sdo_read(device, 0x6502).data == struct.pack("<L", 0x280)
    assert decode_statusword(struct.unpack("<H", sdo_read(device, 0x6041).data)[0]) is (
        State.SWITCH_ON_DISABLED
    )
    device.measure(2.0 + 2 * math.pi * RADIUS, -0.1)  # one drum turn out, direction -1
    assert struct.unpack("<l", sdo_read(device, 0x6064).data)[0] == round(
        device.scaling.position(2.0 + 2 * math.pi * RADIUS)
    )
    assert struct.unpack("<l", sdo_read(device, 0x6064).data)[0] == -8 * (1 << 17) + round(
        device.scaling.position(2.0)
    )
    assert struct.unpack("<l", sdo_read(device, 0x606C).data)[0] > 0  # paying in is +rotation


@pytest.mark.parametrize(
    ("request_frame", "abort"),
    [
        (codec.encode_sdo_upload_request(NODE, 0x1234, 0), 0x06020000),
        (codec.encode_sdo_upload_request(NODE, 0x1018, 9), 0x06090011),
        (codec.encode_sdo_upload_request(NODE, 0x6041, 1), 0x06090011),
        (codec.encode_sdo_download_request(NODE, 0x6041, 0, b"\x06\x00"), 0x06010002),
        (codec.encode_sdo_download_request(NODE, 0x6076, 0, b"\x01\x00\x00\x00"), 0x06010002),
        (codec.encode_sdo_download_request(NODE, 0x6060, 0, b"\x0a\x00"), 0x06070010),
        (codec.encode_sdo_download_request(NODE, 0x6060, 0, b"\x09"), 0x06090030),
        (codec.encode_sdo_download_request(NODE, 0x6060, 0, b"\x0b"), 0x06090030),
        (codec.encode_sdo_download_request(NODE, 0x6072, 0, b"\xff\xff"), 0x06090031),
        (codec.encode_sdo_download_request(NODE, 0x6007, 0, b"\x04\x00"), 0x06090031),
        (codec.encode_sdo_download_request(NODE, 0x2000, 0, b"\x01"), 0x06020000),
        (codec.message(0x600 + NODE, b"\x21\x00\x10\x00\x08\x00\x00\x00"), 0x06010002),
        (codec.message(0x600 + NODE, b"\xa0\x00\x10\x00\x00\x00\x00\x00"), 0x05040001),
    ],
)
def test_sdo_aborts(request_frame: can.Message, abort: int) -> None:
    device = drive()
    before = dict(device.values)
    (answer,) = send(device, request_frame)
    sdo = codec.decode_sdo_response(answer.arbitration_id, answer.data)
    assert (sdo.kind, sdo.abort_code) == (SdoKind.ABORT, abort)
    assert (sdo.index, sdo.subindex) == struct.unpack_from("<HB", request_frame.data, 1)
    assert device.values == before


def test_sdo_downloads_configure_the_drive() -> None:
    device = drive(has_holding_brake=True)
    assert sdo_write(device, 0x1400, 5, struct.pack("<H", 20)).kind is SdoKind.DOWNLOAD
    assert device.rpdo_deadlines == {"RPDO1": 0.02, "RPDO2": 0.1}
    sdo_write(device, 0x1005, 0, struct.pack("<L", 0x81))
    assert send(device, codec.encode_sync()) == [] and len(send(device, codec.message(0x81))) == 2
    assert send(device, codec.message(0x600 + NODE, b"\x80\x00\x10\x00\x00\x00\x00\x00")) == []


# -- state machine, actuation, scaling ------------------------------------------------------


def test_controlword_walks_the_402_machine_and_sets_the_power_stage() -> None:
    device = drive(has_holding_brake=True)
    assert device.actuation is Actuation.OFF and device.brake_engaged
    rpdo1(device, Command.SHUTDOWN.value)
    assert device.state is State.READY_TO_SWITCH_ON and device.brake_engaged
    rpdo1(device, Command.SWITCH_ON.value)
    assert device.state is State.SWITCHED_ON and device.actuation is Actuation.OFF
    rpdo1(device, Command.ENABLE_OPERATION.value, -400)
    assert device.state is State.OPERATION_ENABLED and not device.brake_engaged
    assert device.actuation is Actuation.TORQUE
    # -400 per mille of 1.5 N·m = -0.6 N·m; force = dir * T * gear / r = 0.6 * 8 / 0.04
    assert device.force == pytest.approx(120.0)
    rpdo1(device, Command.SWITCH_ON.value)  # disable operation
    assert device.state is State.SWITCHED_ON and device.brake_engaged
    rpdo1(device, Command.ENABLE_OPERATION.value)
    rpdo1(device, Command.DISABLE_VOLTAGE.value)
    assert device.state is State.SWITCH_ON_DISABLED and device.actuation is Actuation.OFF


def test_torque_is_clamped_to_the_max_torque() -> None:
    device = drive()
    sdo_write(device, 0x6072, 0, struct.pack("<H", 1000))
    enable(device)
    rpdo1(device, 0x0F, 32767)
    assert device.force == pytest.approx(-1.5 * 8 / RADIUS)  # rated torque, direction -1
    rpdo1(device, 0x0F, -32768)
    assert device.force == pytest.approx(1.5 * 8 / RADIUS)


def test_position_mode_and_sync_feedback() -> None:
    device = drive()
    enable(device)
    target = round(device.scaling.position(2.25))
    rpdo2(device, 0x0F, target)
    assert device.actuation is Actuation.POSITION
    assert device.target_length == pytest.approx(2.25, abs=1e-6)
    device.measure(2.1, 0.5)
    tpdo1, tpdo2 = send(device, codec.encode_sync())
    statusword, position, mode = codec.decode_tpdo1(tpdo1.arbitration_id, tpdo1.data)
    assert decode_statusword(statusword) is State.OPERATION_ENABLED and mode == MODE_CSP
    assert position == round(device.scaling.position(2.1))
    assert codec.decode_tpdo2(tpdo2.arbitration_id, tpdo2.data) == round(
        device.scaling.velocity(0.5)
    )
    device.measure(1e9, -1e9)  # an encoder saturates at the i32 range
    tpdo1, tpdo2 = send(device, codec.encode_sync())
    assert codec.decode_tpdo1(tpdo1.arbitration_id, tpdo1.data)[1] == -(2**31)
    assert codec.decode_tpdo2(tpdo2.arbitration_id, tpdo2.data) == 2**31 - 1


def test_switching_to_position_mode_without_a_target_holds_the_actual_position() -> None:
    device = drive()
    enable(device)
    device.measure(2.3, 0.0)
    rpdo1(device, 0x0F, 0, mode=MODE_CSP)  # RPDO1 carries no position
    assert device.actuation is Actuation.POSITION
    assert device.target_length == pytest.approx(2.3, abs=1e-6)
    rpdo1(device, 0x0F, 0, mode=MODE_CST)
    device.measure(2.4, 0.0)
    assert sdo_write(device, 0x6060, 0, bytes((MODE_CSP,))).kind is SdoKind.DOWNLOAD
    assert device.target_length == pytest.approx(2.4, abs=1e-6)


def test_objects_without_a_value_answer_no_data(tmp_path: Path) -> None:
    text = EDS_PATH.read_text().replace(
        "[1005]",
        "[1009]\nParameterName=Manufacturer hardware version\nObjectType=0x7\nDataType=0x0009\n"
        "AccessType=const\nPDOMapping=0\n\n[1005]",
    )
    eds = tmp_path / "named.eds"
    eds.write_text(text)
    config = parse_drives({"protocol": "cia402", "nodes": [NODE], "rated_torque": 1.0})
    device = Cia402Drive(NODE, config.scalings([RADIUS])[0], config, eds=eds)
    device.on_tick(0.0)
    assert sdo_read(device, 0x1009).abort_code == 0x08000024


def test_a_fresh_drive_has_the_vendor_default_mapping_and_no_manufacturer_objects() -> None:
    device = drive(mapped=False)
    assert sdo_read(device, 0x1600, 0).data == b"\x01"
    assert sdo_read(device, 0x1600, 1).data == struct.pack("<L", 0x60400010)
    assert sdo_read(device, 0x1A00, 1).data == struct.pack("<L", 0x60410010)
    assert sdo_read(device, 0x1801, 1).data == struct.pack("<L", 0x80000280 + NODE)
    assert [sdo_read(device, index).abort_code for index in (0x2000, 0x2001)] == [0x06020000] * 2
    # SYNC: TPDO1 (statusword only, type 255 = not on SYNC) -> nothing yet
    assert send(device, codec.encode_sync()) == []
    # the old 5-byte RPDO1 is not what RPDO1 maps now: a length error, no state change
    rpdo1(device, 0x06)
    assert device.counters.rejected == {"RPDO1 length": 1}
    send(device, codec.message(0x200 + NODE, b"\x06\x00"))  # controlword alone
    assert device.state is State.READY_TO_SWITCH_ON


def test_the_mapping_changes_only_by_the_cia301_procedure() -> None:
    device = drive(mapped=False)
    # RPDO1 valid: its mapping is locked
    assert sdo_write(device, 0x1600, 0, b"\x00").abort_code == 0x08000022
    assert sdo_write(device, 0x1400, 1, struct.pack("<L", 0x300 + NODE)).abort_code == 0x06090030
    assert sdo_write(device, 0x1400, 1, struct.pack("<L", 0x80000200 + NODE)).abort_code == 0
    # invalid, but sub0 still 1: entries are locked
    assert sdo_write(device, 0x1600, 2, struct.pack("<L", 0x60710010)).abort_code == 0x08000022
    assert sdo_write(device, 0x1600, 0, b"\x00").abort_code == 0
    assert sdo_write(device, 0x1600, 2, struct.pack("<L", 0x60710010)).abort_code == 0
    assert sdo_write(device, 0x1600, 3, struct.pack("<L", 0x10080000 | 8)).abort_code == 0
    assert sdo_write(device, 0x1600, 0, b"\x03").abort_code == 0x06040041  # a string
    assert sdo_write(device, 0x1600, 3, struct.pack("<L", 0x60410010)).abort_code == 0
    assert sdo_write(device, 0x1600, 0, b"\x03").abort_code == 0x06040041  # read-only
    for k in range(3, 6):
        assert sdo_write(device, 0x1600, k, struct.pack("<L", 0x607A0020)).abort_code == 0
    assert sdo_write(device, 0x1600, 0, b"\x05").abort_code == 0x06040042  # 16 bytes
    assert sdo_write(device, 0x1600, 0, b"\x03").abort_code == 0
    assert sdo_write(device, 0x1400, 1, struct.pack("<L", 0x200 + NODE)).abort_code == 0
    send(device, codec.message(0x200 + NODE, struct.pack("<Hhi", 0x06, 7, 1234)))
    assert device.state is State.READY_TO_SWITCH_ON and device.target_torque == 7
    assert device.values[(0x607A, 0)] == 1234


def test_segmented_upload_and_download() -> None:
    device = drive()
    first = sdo_read(device, 0x1008)
    assert first.kind is SdoKind.UPLOAD and first.size == len("cdprd CiA 402 CST winch drive")
    name, toggle = b"", 0
    for _ in range(10):
        (answer,) = send(device, codec.encode_sdo_segment_ask(NODE, toggle, server=False))
        segment = codec.decode_sdo_response(answer.arbitration_id, answer.data)
        assert segment.kind is SdoKind.SEGMENT and segment.toggle == toggle
        name += segment.data
        toggle ^= 1
        if segment.last:
            break
    assert name == b"cdprd CiA 402 CST winch drive"
    # a wrong toggle bit aborts
    sdo_read(device, 0x1008)
    (answer,) = send(device, codec.encode_sdo_segment_ask(NODE, 1, server=False))
    assert codec.decode_sdo_response(answer.arbitration_id, answer.data).abort_code == 0x05030000
    # segmented download of a 4-byte object: stored once the last segment came
    (answer,) = send(device, codec.encode_sdo_download_initiate(NODE, 0x607A, 0, 4))
    assert codec.decode_sdo_response(answer.arbitration_id, answer.data).kind is SdoKind.DOWNLOAD
    (answer,) = send(
        device, codec.encode_sdo_segment(NODE, 0, b"\x10\x27\x00\x00", True, server=False)
    )
    assert codec.decode_sdo_response(answer.arbitration_id, answer.data).kind is SdoKind.SEGMENT_ASK
    assert device.values[(0x607A, 0)] == 10000


@pytest.mark.parametrize(
    ("option", "quick_stop", "brake", "state", "actuation"),
    [
        (3, 6, False, State.QUICK_STOP_ACTIVE, Actuation.POSITION),  # holds
        (3, 2, False, State.SWITCH_ON_DISABLED, Actuation.OFF),  # falls: no brake
        (3, 2, True, State.SWITCH_ON_DISABLED, Actuation.OFF),  # brake engaged
        (2, 6, False, State.SWITCH_ON_DISABLED, Actuation.OFF),
        (1, 6, False, State.FAULT, Actuation.POSITION),  # the fault reaction holds
    ],
)
def test_a_lost_host_heartbeat_reacts_by_0x6007_and_0x605a(
    option: int, quick_stop: int, brake: bool, state: State, actuation: Actuation
) -> None:
    device = drive(has_holding_brake=brake)
    sdo_write(device, 0x1400, 5, b"\x00\x00")  # no RPDO deadline: only the heartbeat
    sdo_write(device, 0x1016, 1, struct.pack("<L", 127 << 16 | 200))
    sdo_write(device, 0x6007, 0, struct.pack("<h", option))
    sdo_write(device, 0x605A, 0, struct.pack("<h", quick_stop))
    enable(device)
    rpdo1(device, 0x0F, 100, 0.0, mode=MODE_CST)
    assert device.on_tick(1.0) == []  # not armed before the first heartbeat
    host_beat = codec.encode_heartbeat(127, NmtState.OPERATIONAL)
    send(device, host_beat, 1.0)
    assert device.on_tick(1.19) == [] and device.state is State.OPERATION_ENABLED
    out = device.on_tick(1.21)
    assert 0x8130 in emcy_codes(out)
    assert device.state is state and device.actuation is actuation
    assert device.brake_engaged is brake
    if actuation is Actuation.POSITION:
        assert device.target_length == pytest.approx(2.0, abs=1e-6)


def test_fault_reset_needs_a_rising_edge_and_the_cause_gone() -> None:
    device = drive()
    enable(device)
    assert emcy_codes(device.inject_fault(0x2310, "overcurrent", persistent=True)) == [0x2310]
    assert device.state is State.FAULT and device.actuation is Actuation.POSITION
    assert rpdo1(device, 0x0F) == [] and device.state is State.FAULT  # ignored in FAULT
    assert rpdo1(device, 0x80) == [] and device.state is State.FAULT  # cause persists
    device.clear_fault_cause()
    assert rpdo1(device, 0x80) == [] and device.state is State.FAULT  # no rising edge
    rpdo1(device, 0x00)
    assert emcy_codes(rpdo1(device, 0x80)) == [0]  # error reset EMCY
    assert device.state is State.SWITCH_ON_DISABLED and device.fault_code == 0
    assert device.actuation is Actuation.POSITION and device.target_length == 2.0  # holds
    word = struct.unpack("<H", sdo_read(device, 0x6041).data)[0]
    assert word & STATUS_HOLD
    rpdo1(device, 0x06)
    rpdo1(device, 0x07)
    assert device.actuation is Actuation.POSITION  # shutdown / switch on keep the hold
    rpdo1(device, Command.DISABLE_VOLTAGE.value | CONTROL_RELEASE_HOLD)
    assert device.actuation is Actuation.OFF and device.hold is None


def test_a_fault_does_not_power_up_a_disabled_drive() -> None:
    device = drive(has_holding_brake=True)
    assert emcy_codes(device.inject_fault(0x3210, "DC link overvoltage")) == [0x3210]
    assert device.state is State.FAULT and device.hold is None
    assert device.actuation is Actuation.OFF and device.brake_engaged
    with pytest.raises(ValueError, match="non-zero u16"):
        device.inject_fault(0, "nothing")


@pytest.mark.parametrize("brake", ["position_hold", "holding_brake"])
def test_quick_stop_brakes_and_never_ramps_torque_to_zero(brake: str) -> None:
    device = drive(brake=brake, has_holding_brake=True)
    enable(device)
    rpdo1(device, 0x0F, -300)
    device.measure(2.05, 0.2)
    rpdo1(device, Command.QUICK_STOP.value)
    assert device.state is State.QUICK_STOP_ACTIVE
    if brake == "position_hold":
        assert device.actuation is Actuation.POSITION and device.target_length == 2.05
    else:
        assert device.actuation is Actuation.OFF and device.brake_engaged
    rpdo1(device, 0x0F, -300)  # transition 16 back to operation enabled
    assert device.state is State.OPERATION_ENABLED and device.actuation is Actuation.TORQUE


# -- RPDO deadline ---------------------------------------------------------------------------


def test_rpdo_deadline_faults_and_holds_where_the_deadline_expired() -> None:
    device = drive()
    assert device.on_tick(5.0) == []  # no RPDO yet: nothing to watch
    for word in (0x06, 0x07, 0x0F):  # enabled through SDO: not armed either
        sdo_write(device, 0x6040, 0, struct.pack("<H", word), 5.0)
    assert device.state is State.OPERATION_ENABLED and device.on_tick(6.0) == []
    rpdo1(device, 0x0F, 10, now=6.0)
    assert device.on_tick(6.099) == []
    rpdo1(device, 0x0F, 10, now=6.099)  # fed
    assert device.on_tick(6.19) == []
    device.measure(2.2, 0.0)
    assert emcy_codes(device.on_tick(6.2)) == [0x8250]
    assert device.state is State.FAULT and device.fault_code == 0x8250
    assert device.fault_text == "no RPDO1 within its deadline 0x1400:05"
    assert device.actuation is Actuation.POSITION and device.target_length == 2.2
    assert struct.unpack("<B", sdo_read(device, 0x1001).data)[0] == 0x11
    assert struct.unpack("<H", sdo_read(device, 0x603F).data)[0] == 0x8250
    assert device.on_tick(10.0) == []  # off until RPDO1 comes again: one EMCY


def test_each_rpdo_has_its_own_deadline_from_its_first_reception() -> None:
    """CiA 301: an RPDO's event timer watches that RPDO only.  RPDO2 (the hold) once,
    then RPDO1 (torque) every 10 ms: RPDO1 does not feed RPDO2's deadline, which expires
    100 ms after RPDO2 came, as a real drive's does after a hold -> torque switch."""
    device = drive()
    assert device.rpdo_deadlines == {"RPDO1": 0.1, "RPDO2": 0.1}
    enable(device, now=1.0)
    rpdo2(device, 0x0F, device._position(), now=1.0)
    out, t = [], 1.0
    for k in range(1, 20):  # 190 ms of torque control
        t = 1.0 + 0.01 * k
        out += rpdo1(device, 0x0F, 50, now=t) + device.on_tick(t + 0.005)
        if device.state is State.FAULT:
            break
    assert emcy_codes(out) == [0x8250] and t == pytest.approx(1.1)
    assert device.fault_text == "no RPDO2 within its deadline 0x1401:05"


def test_an_rpdo_deadline_never_armed_never_fires_and_runs_in_every_402_state() -> None:
    device = drive()
    enable(device, now=1.0)
    for k in range(1, 200):  # RPDO1 alone for 2 s: RPDO2's deadline was never armed
        assert rpdo1(device, 0x0F, 50, now=1.0 + 0.01 * k) == []
        assert device.on_tick(1.005 + 0.01 * k) == []
    assert device.state is State.OPERATION_ENABLED
    # a deadline is CiA 301's, not the 402 state's: armed in READY TO SWITCH ON too
    device = drive()
    rpdo1(device, Command.SHUTDOWN.value, now=1.0)
    assert device.state is State.READY_TO_SWITCH_ON and device.on_tick(1.099) == []
    assert emcy_codes(device.on_tick(1.1)) == [0x8250] and device.state is State.FAULT
    # leaving OPERATIONAL stops it; after NMT start it waits for the next reception
    device = drive()
    enable(device, now=1.0)
    send(device, codec.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE), 1.05)
    send(device, codec.encode_nmt(NmtCommand.START, NODE), 1.06)
    assert device.on_tick(5.0) == [] and device.state is State.OPERATION_ENABLED
    # so does 0x14xx:05 = 0 while armed
    device = drive()
    enable(device, now=1.0)
    sdo_write(device, 0x1400, 5, b"\x00\x00", 1.05)
    assert device.on_tick(5.0) == [] and device.state is State.OPERATION_ENABLED


def test_rpdo_deadline_with_holding_brake_and_disabled_deadline() -> None:
    device = drive(brake="holding_brake", has_holding_brake=True)
    enable(device, now=1.0)
    late = rpdo1(device, 0x0F, 100, now=1.2)  # arrives after the 100 ms deadline
    assert emcy_codes(late) == [0x8250] and device.state is State.FAULT
    assert device.actuation is Actuation.OFF and device.brake_engaged
    device = drive()
    sdo_write(device, 0x1400, 5, b"\x00\x00")
    enable(device)
    assert device.on_tick(100.0) == [] and device.state is State.OPERATION_ENABLED


def test_power_on_hold_until_enabled_or_released() -> None:
    device = drive(power_on_hold=True)
    assert device.hold is BrakeMode.POSITION_HOLD and device.target_length == 2.0
    assert device.actuation is Actuation.POSITION
    enable(device)
    assert device.hold is None and device.actuation is Actuation.TORQUE


# -- hostile frames --------------------------------------------------------------------------

HOSTILE = [
    (0x200 + NODE, b"\x0f\x00\x00\x00", "RPDO1 length"),
    (0x200 + NODE, b"\x0f\x00\x00\x00\x0a\x00", "RPDO1 length"),
    (0x200 + NODE, struct.pack("<Hhb", 0x0F, 0, 1), "mode of operation"),
    (0x300 + NODE, b"\x0f\x00\x00\x00\x00\x00", "RPDO2 length"),
    (0x300 + NODE, struct.pack("<Hib", 0x0F, 0, -8), "mode of operation"),
    (0x600 + NODE, b"\x40\x41\x60\x00", "SDO length"),
    (0x000, b"\x01", "NMT length"),
    (0x000, b"\x07\x05", "NMT command"),
    (0x000, b"\x01\x85", "NMT node"),
    (0x080, b"\x01\x02", "SYNC length"),
]


@pytest.mark.parametrize(("can_id", "data", "reason"), HOSTILE)
def test_malformed_frames_are_counted_and_ignored(can_id: int, data: bytes, reason: str) -> None:
    device = drive()
    enable(device)
    rpdo1(device, 0x0F, 123)
    before = (device.state, device.actuation, device.force, dict(device.values), device.nmt_state)
    assert send(device, codec.message(can_id, data), 0.01) == []
    assert device.counters.rejected == {reason: 1}
    assert (device.state, device.actuation, device.force, device.values, device.nmt_state) == before


def test_remote_extended_and_foreign_frames() -> None:
    device = drive()
    remote = can.Message(arbitration_id=0x200 + NODE, is_remote_frame=True, is_extended_id=False)
    assert send(device, remote) == [] and device.counters.rejected == {"remote frame": 1}
    ext = can.Message(arbitration_id=0x200 + NODE, data=b"\x06\x00\x00\x00\x0a")
    assert send(device, ext) == [] and device.state is State.SWITCH_ON_DISABLED
    for foreign in (0x200 + NODE + 1, 0x180 + NODE, 0x580 + NODE, 0x700 + NODE, 0x7FF):
        assert send(device, codec.message(foreign, b"\x06\x00\x00\x00\x0a")) == []
    assert device.counters.rejected_total == 1 and device.state is State.SWITCH_ON_DISABLED


@given(
    st.lists(
        st.tuples(
            st.sampled_from([0x000, 0x080, 0x200 + NODE, 0x300 + NODE, 0x600 + NODE, 0x7FF]),
            st.binary(max_size=9),
        ),
        max_size=40,
    )
)
def test_garbage_floods_never_crash_the_drive(frames: list[tuple[int, bytes]]) -> None:
    device = drive()
    device.counters.accepted = 0
    for k, (can_id, data) in enumerate(frames):
        for answer in send(device, codec.message(can_id, data), k * 1e-3):
            assert not answer.is_extended_id and len(answer.data) <= 8
        device.on_tick(k * 1e-3)
    assert device.counters.accepted + device.counters.rejected_total <= len(frames)


@given(st.lists(st.sampled_from(HOSTILE), max_size=60))
def test_malformed_floods_change_nothing(frames: list[tuple[int, bytes, str]]) -> None:
    device = drive()
    enable(device)
    before = (device.state, device.actuation, device.force, dict(device.values))
    for can_id, data, _ in frames:
        assert send(device, codec.message(can_id, data), 0.01) == []
    assert device.counters.rejected_total == len(frames)
    assert (device.state, device.actuation, device.force, device.values) == before


# -- the compact layout: a shared RPDO (dummy entries) and event-driven TPDOs --------------


def no_dummies(tmp_path: Path) -> Path:
    """The drive's EDS with every dummy entry forbidden ([DummyUsage] all 0)."""
    eds = tmp_path / "no_dummies.eds"
    text = EDS_PATH.read_text()
    for k in range(1, 8):
        text = text.replace(f"Dummy000{k}=1", f"Dummy000{k}=0")
    eds.write_text(text)
    return eds


def map_pdo(device: Cia402Drive, comm: int, cob: int, entries: list[int], kind: int) -> int:
    """The CiA 301 procedure; the abort code of the sub0 write that checks the entries."""
    assert sdo_write(device, comm, 1, struct.pack("<L", cob | 0x8000_0000)).abort_code == 0
    assert sdo_write(device, comm, 2, bytes((kind,))).abort_code == 0
    assert sdo_write(device, comm + 0x200, 0, b"\x00").abort_code == 0
    for k, entry in enumerate(entries):
        assert sdo_write(device, comm + 0x200, k + 1, struct.pack("<L", entry)).abort_code == 0
    code = sdo_write(device, comm + 0x200, 0, bytes((len(entries),))).abort_code
    if code == 0:
        assert sdo_write(device, comm, 1, struct.pack("<L", cob)).abort_code == 0
    return code


# node 5 fills slot 1 of four: UNSIGNED16 dummies over the other drives' torques
SHARED = [0x00060010, 0x60710010, 0x00060010, 0x00060010]


def test_a_shared_rpdo_gives_the_drive_its_own_bytes_where_the_eds_allows_dummies(
    tmp_path: Path,
) -> None:
    device = drive(mapped=False)
    device.on_frame(codec.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE), 0.0)
    assert map_pdo(device, 0x1400, 0x201, SHARED, 255) == 0
    assert sdo_write(device, 0x1400, 5, struct.pack("<H", 100)).abort_code == 0
    # a TPDO carries no dummy entry (CiA 301: receive side only)
    assert map_pdo(device, 0x1800, 0x180 + NODE, [0x60410010, 0x00060010], 1) == 0x06040041
    device.on_frame(codec.encode_nmt(NmtCommand.START, NODE), 0.0)
    for word in (0x06, 0x07, 0x0F):
        sdo_write(device, 0x6040, 0, struct.pack("<H", word))
    sdo_write(device, 0x6060, 0, struct.pack("<b", MODE_CST))
    send(device, codec.message(0x201, struct.pack("<hhhh", 11, 22, -33, 44)), 1.0)
    assert device.target_torque == 22 and device.actuation is Actuation.TORQUE
    assert not [key for key in device.values if key[0] < 0x1000]  # the dummies' bytes: dropped
    assert device.on_tick(1.099) == []  # the torque-only RPDO feeds the deadline
    send(device, codec.message(0x201, struct.pack("<hhhh", 0, -5, 0, 0)), 1.099)
    assert device.on_tick(1.19) == [] and device.target_torque == -5
    assert emcy_codes(device.on_tick(1.2)) == [0x8250]
    # the same mapping in a drive whose EDS does not allow dummy entries
    config = parse_drives({"protocol": "cia402", "nodes": [NODE], "rated_torque": 1.0})
    strict = Cia402Drive(NODE, config.scalings([RADIUS])[0], config, eds=no_dummies(tmp_path))
    strict.on_tick(0.0)
    assert map_pdo(strict, 0x1400, 0x201, SHARED, 255) == 0x06040041


def test_an_event_driven_tpdo_goes_out_on_change_at_most_once_per_inhibit_time() -> None:
    device = drive(mapped=False)
    device.on_frame(codec.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, NODE), 0.0)
    assert map_pdo(device, 0x1800, 0x180 + NODE, [0x60640020], 1) == 0
    assert map_pdo(device, 0x1801, 0x280 + NODE, [0x60410010, 0x60610008], 255) == 0
    assert sdo_write(device, 0x1801, 3, struct.pack("<H", 100)).abort_code == 0  # 10 ms
    assert device.on_tick(0.5) == []  # pre-operational: no PDO

    def status(frames: list[can.Message]) -> list[State | None]:
        words = [struct.unpack("<Hb", f.data)[0] for f in frames if f.arbitration_id == 0x285]
        return [decode_statusword(word) for word in words]

    started = device.on_frame(codec.encode_nmt(NmtCommand.START, NODE), 1.0)
    assert status(started) == [State.SWITCH_ON_DISABLED]  # once on entering OPERATIONAL
    assert status(device.on_tick(1.001)) == []  # nothing changed
    sync = send(device, codec.encode_sync(), 1.002)  # position alone on SYNC
    assert [(f.arbitration_id, len(f.data)) for f in sync] == [(0x185, 4)]
    answer = sdo_write(device, 0x6040, 0, struct.pack("<H", 0x06), 1.003)
    assert answer.kind is SdoKind.DOWNLOAD
    assert status(device.on_tick(1.004)) == []  # changed, but within 10 ms of the last
    assert status(device.on_tick(1.011)) == [State.READY_TO_SWITCH_ON]
    assert status(device.on_tick(1.5)) == []
