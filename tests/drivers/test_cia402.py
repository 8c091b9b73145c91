"""CiA 402 host driver and codecs: the EDS against the structs (parsed and decoded with
canopen), the 402 state machine, scaling and signs, hostile frames, and round trips
between a host Cia402Driver and simulated Cia402Drive devices over an in-memory bus in
simulated time (device-only behaviour: tests/drivers/test_cia402_device.py)."""

from __future__ import annotations

import asyncio
import math
import re
import struct
from collections import deque
from collections.abc import Callable
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from cdpr import ConfigError
from cdpr.description import load_yaml
from drivers.base import Actuation, BrakeMode, DriverError, DriveState, FrameError, Timing
from drivers.cia402 import codec
from drivers.cia402.codec import (
    EDS_PATH,
    PDO_LAYOUTS,
    Cia402FrameError,
    NmtCommand,
    NmtState,
    SdoKind,
)
from drivers.cia402.host import Cia402Driver
from drivers.cia402.statemachine import (
    CONTROL_RELEASE_HOLD,
    MODE_CSP,
    MODE_CST,
    STATUS_HOLD,
    Command,
    State,
    decode_command,
    decode_statusword,
    drive_state,
    encode_statusword,
    next_state,
)
from drivers.config import DrivesConfig, parse_drives
from sim_bus.devices.cia402 import Cia402Drive
from tests.drivers.test_cia402_device import no_dummies

RADIUS = 0.05


# -- an in-memory bus in simulated time ------------------------------------------------------


class MemoryLink:
    """Host frames reach every device at once; device frames queue for the host and reach
    `driver.receive` when `expect` or `deliver` drains them.  `expect` advances simulated
    time in 1 ms ticks (devices tick: heartbeats, RPDO deadlines) until a match or its
    timeout.  `mute` silences devices (by node id) as a dead node would be; `drop` loses
    the device frames it is true for."""

    def __init__(self, driver: Cia402Driver, devices: list[Cia402Drive]) -> None:
        self.driver, self.devices = driver, devices
        self.t = 0.0
        self.queue: deque[can.Message] = deque()
        self.sent: list[can.Message] = []
        self.mute: set[int] = set()
        self.drop: Callable[[can.Message], bool] = lambda message: False
        self.every_tick: Callable[[], None] = lambda: None  # e.g. the daemon's cycle
        self.advance(0.0)

    def _from(self, device: Cia402Drive, frames: list[can.Message]) -> None:
        if device.node_id not in self.mute:
            self.queue.extend(m for m in frames if not self.drop(m))

    def send(self, message: can.Message) -> None:
        self.sent.append(message)
        for device in self.devices:
            self._from(device, device.on_frame(message, self.t))

    def deliver(self) -> list[int | None]:
        results = []
        while self.queue:
            results.append(self.driver.receive(self.queue.popleft(), self.t))
        return results

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        deadline = self.t + timeout
        self.every_tick()  # the bus is shared: other frames may go out between two steps
        while True:
            while self.queue:
                message = self.queue.popleft()
                self.driver.receive(message, self.t)
                if match(message):
                    return message
            if self.t >= deadline:
                raise DriverError(f"timed out waiting for {what}")
            self.advance(0.001)

    def advance(self, dt: float) -> None:
        self.t += dt
        self.every_tick()
        for device in self.devices:
            self._from(device, device.on_tick(self.t))

    def run(self, coroutine) -> None:
        asyncio.run(coroutine)

    def cycle(self, forces: list[float] | None = None) -> list[int | None]:
        """One SYNC cycle: SYNC, feedback to the host, then commands (if given)."""
        for frame in self.driver.cycle_start():
            self.send(frame)
        done = self.deliver()
        if forces is not None:
            for frame in self.driver.commands(forces):
                self.send(frame)
        return done


def drives_config(**overrides) -> DrivesConfig:
    data = {
        "protocol": "cia402",
        "nodes": [1, 2, 3],
        "rated_torque": 2.0,
        "gear_ratio": 10.0,
        "counts_per_rev": 4096,
        "direction": [1, -1, 1],
        "length_offset": [1.0, 2.0, 0.5],
    }
    data.update(overrides)
    return parse_drives(data)


def make_bus(lengths: list[float] | None = None, *, started: bool = True, **overrides):
    config = drives_config(**overrides)
    scalings = config.scalings([RADIUS] * len(config.nodes))
    driver = Cia402Driver(config, scalings)
    devices = [Cia402Drive(node, s, config) for node, s in zip(config.nodes, scalings, strict=True)]
    for device, length in zip(devices, lengths or [1.5] * len(devices), strict=True):
        device.measure(length, 0.0)
    link = MemoryLink(driver, devices)
    if started:
        link.run(driver.start(link, lambda: link.t))
    return driver, devices, link


def permille(driver: Cia402Driver, i: int, force: float) -> float:
    return driver.scalings[i].motor_torque(force) / driver.config.rated_torque * 1000.0


# -- the EDS against the codec -------------------------------------------------------------


def canopen_node(node: int) -> canopen.RemoteNode:
    """canopen's view of a drive mapped as the default profile maps it (its own PDO API)."""
    remote = canopen.RemoteNode(node, codec.load_eds(EDS_PATH, node))
    canopen.Network().add_node(remote)
    for layout in PDO_LAYOUTS:
        maps = remote.rpdo if layout.receive else remote.tpdo
        pdo = maps[int(layout.name[-1])]
        pdo.clear()
        for entry in layout.entries:
            pdo.add_variable(entry.index, entry.subindex, entry.bits)
        pdo.cob_id, pdo.trans_type, pdo.enabled = (
            layout.cob_id(node),
            layout.transmission_type,
            True,
        )
    return remote


def test_pdo_layouts_from_the_eds_match_the_codec_and_canopen() -> None:
    od = codec.load_eds(EDS_PATH, 3)
    for layout in PDO_LAYOUTS:
        objects = [(e.index, e.subindex) for e in layout.entries]
        number = int(layout.name[-1])
        built = codec.pdo_layout(od, layout.receive, number, objects, layout.transmission_type)
        assert (built.name, built.cob_base, built.comm_index, built.map_index) == (
            layout.name,
            layout.cob_base,
            layout.comm_index,
            layout.map_index,
        )
        assert (built.entries, built.struct.format) == (layout.entries, layout.struct.format)
    node = canopen_node(3)
    for layout in PDO_LAYOUTS:
        pdo = (node.rpdo if layout.receive else node.tpdo)[int(layout.name[-1])]
        fields = layout.struct.format.lstrip("<")
        offsets = [struct.calcsize("<" + fields[:k]) * 8 for k in range(len(fields))]
        assert [(v.index, v.subindex, v.offset, v.length) for v in pdo.map] == [
            (e.index, e.subindex, offset, e.bits)
            for e, offset in zip(layout.entries, offsets, strict=True)
        ]
        assert pdo.length == layout.struct.size * 8 <= 64


def test_canopen_decodes_our_frames_and_encodes_like_us() -> None:
    node = canopen_node(7)
    network = node.network
    network.subscribe(0x187, node.tpdo[1].on_message)
    network.subscribe(0x287, node.tpdo[2].on_message)
    tpdo1 = codec.encode_tpdo1(7, 0x4237, -123456, MODE_CSP)
    tpdo2 = codec.encode_tpdo2(7, 98765)
    for frame in (tpdo1, tpdo2):
        network.notify(frame.arbitration_id, frame.data, 0.0)
    assert node.tpdo[1][0x6041].raw == 0x4237
    assert node.tpdo[1][0x6064].raw == -123456
    assert node.tpdo[1][0x6061].raw == MODE_CSP
    assert node.tpdo[2][0x606C].raw == 98765
    rpdo1, rpdo2 = node.rpdo[1], node.rpdo[2]
    rpdo1[0x6040].raw, rpdo1[0x6071].raw, rpdo1[0x6060].raw = 0x0F, -250, MODE_CST
    rpdo2[0x6040].raw, rpdo2[0x607A].raw, rpdo2[0x6060].raw = 0x0F, -7_000_000, MODE_CSP
    assert bytes(rpdo1.data) == bytes(codec.encode_rpdo1(7, 0x0F, -250, MODE_CST).data)
    assert bytes(rpdo2.data) == bytes(codec.encode_rpdo2(7, 0x0F, -7_000_000, MODE_CSP).data)


def test_a_profile_the_eds_refuses_is_named(tmp_path: Path) -> None:
    text = EDS_PATH.read_text()
    retyped = tmp_path / "retyped.eds"
    section = text.index("[6071]")
    retyped.write_text(text[:section] + text[section:].replace("PDOMapping=1", "PDOMapping=0", 1))
    config = drives_config(profile={"eds": str(retyped)})
    with pytest.raises(
        ValueError, match=r"profile.rpdo.0.objects.1: 0x6071:00 .* not PDO-mappable"
    ):
        Cia402Driver(config, config.scalings([RADIUS] * 3))
    cases = [
        (
            {"sdo_writes": [{"object": "0x6072", "value": 40000}]},
            r"sdo_writes.0: 0x6072:00 .* outside 0..32767",
        ),
        ({"sdo_writes": [{"object": "0x6041", "value": 1}]}, r"sdo_writes.0: 0x6041:00 .* is ro"),
        (
            {"sdo_writes": [{"object": "0x2000", "value": 1}]},
            r"sdo_writes.0: object 0x2000:00 is not in the EDS",
        ),
        (  # the host's own safety objects: a dead daemon would leave the drive running
            {"sdo_writes": [{"object": "0x6072", "value": 1000}, {"object": "0x6007", "value": 0}]},
            r"sdo_writes.1: 0x6007:00 .* = 0: the host sets this object itself",
        ),
        (
            {"sdo_writes": [{"object": "0x1016:01", "value": 0}]},
            r"sdo_writes.0: 0x1016:01 .* the host sets this object itself",
        ),
        (
            {"sdo_writes": [{"object": "0x1A00:01", "value": 0x60410010}]},
            r"sdo_writes.0: 0x1A00:01 .* the host sets this object itself",
        ),
        (
            {
                "tpdo": [
                    {"number": 1, "objects": [0x6041, 0x6064], "transmission_type": 1},
                    {"number": 2, "objects": [0x606C], "transmission_type": 1},
                ]
            },
            r"profile.tpdo: no TPDO maps 0x6061",
        ),
        (
            {
                "rpdo": [
                    {
                        "number": 1,
                        "objects": [0x6040, 0x607A, 0x6071, 0x6060],
                        "transmission_type": 255,
                    }
                ]
            },
            r"profile.rpdo.0.objects: 9 bytes",
        ),
        (
            {
                "tpdo": [
                    {"number": 1, "objects": [0x6041, 0x6064, 0x6061], "transmission_type": 0},
                    {"number": 2, "objects": [0x606C], "transmission_type": 1},
                ]
            },
            r"profile.tpdo.0.transmission_type",
        ),
    ]
    for profile, message in cases:
        config = drives_config(profile=profile)
        with pytest.raises(ValueError, match=message):
            Cia402Driver(config, config.scalings([RADIUS] * 3))


# -- codec round trips and hostile bytes ---------------------------------------------------

u16 = st.integers(0, 0xFFFF)
i16 = st.integers(-0x8000, 0x7FFF)
i32 = st.integers(-0x8000_0000, 0x7FFF_FFFF)
nodes = st.integers(1, 127)
modes = st.sampled_from([MODE_CSP, MODE_CST])
valid_statuswords = st.builds(
    lambda state, hold, high: encode_statusword(state, hold) | (high & 0x3F80 & ~STATUS_HOLD),
    st.sampled_from(list(State)),
    st.booleans(),
    u16,
)


@given(nodes, u16, i16, modes)
def test_rpdo1_round_trip(node: int, controlword: int, torque: int, mode: int) -> None:
    frame = codec.encode_rpdo1(node, controlword, torque, mode)
    assert frame.arbitration_id == 0x200 + node and not frame.is_extended_id
    assert codec.decode_rpdo1(frame.arbitration_id, frame.data) == (controlword, torque, mode)


@given(nodes, u16, i32, modes)
def test_rpdo2_round_trip(node: int, controlword: int, position: int, mode: int) -> None:
    frame = codec.encode_rpdo2(node, controlword, position, mode)
    assert frame.arbitration_id == 0x300 + node
    assert codec.decode_rpdo2(frame.arbitration_id, frame.data) == (controlword, position, mode)


@given(nodes, valid_statuswords, i32, modes, i32)
def test_tpdo_round_trips(
    node: int, statusword: int, position: int, mode: int, velocity: int
) -> None:
    tpdo1 = codec.encode_tpdo1(node, statusword, position, mode)
    tpdo2 = codec.encode_tpdo2(node, velocity)
    assert (tpdo1.arbitration_id, tpdo2.arbitration_id) == (0x180 + node, 0x280 + node)
    assert codec.decode_tpdo1(tpdo1.arbitration_id, tpdo1.data) == (statusword, position, mode)
    assert codec.decode_tpdo2(tpdo2.arbitration_id, tpdo2.data) == velocity


@given(nodes, u16, st.integers(0, 255), st.binary(min_size=5, max_size=5))
def test_emcy_round_trip(node: int, code: int, register: int, extra: bytes) -> None:
    frame = codec.encode_emcy(node, code, register, extra)
    assert frame.arbitration_id == 0x80 + node
    assert codec.decode_emcy(frame.arbitration_id, frame.data) == (code, register, extra)


@given(nodes, st.sampled_from(list(NmtState)), st.sampled_from(list(NmtCommand)))
def test_nmt_and_heartbeat_round_trips(node: int, state: NmtState, command: NmtCommand) -> None:
    beat = codec.encode_heartbeat(node, state)
    assert codec.decode_heartbeat(beat.arbitration_id, beat.data) is state
    order = codec.encode_nmt(command, node)
    assert order.arbitration_id == 0 and codec.decode_nmt(order.data) == (command, node)
    assert codec.encode_sync().arbitration_id == 0x80 and not codec.encode_sync().data


@given(
    nodes, u16, st.integers(0, 255), st.binary(min_size=1, max_size=4), st.integers(0, 2**32 - 1)
)
def test_sdo_round_trips(node: int, index: int, sub: int, data: bytes, abort: int) -> None:
    upload = codec.encode_sdo_upload_request(node, index, sub)
    assert upload.arbitration_id == 0x600 + node
    assert codec.decode_sdo_request(upload.arbitration_id, upload.data) == codec.Sdo(
        SdoKind.UPLOAD, index, sub
    )
    download = codec.encode_sdo_download_request(node, index, sub, data)
    assert codec.decode_sdo_request(0x600 + node, download.data) == codec.Sdo(
        SdoKind.DOWNLOAD, index, sub, data
    )
    answer = codec.encode_sdo_upload_response(node, index, sub, data)
    assert answer.arbitration_id == 0x580 + node
    assert codec.decode_sdo_response(answer.arbitration_id, answer.data).data == data
    confirm = codec.encode_sdo_download_response(node, index, sub)
    assert codec.decode_sdo_response(0x580 + node, confirm.data).kind is SdoKind.DOWNLOAD
    refused = codec.encode_sdo_abort(node, index, sub, abort, server=True)
    assert codec.decode_sdo_response(0x580 + node, refused.data) == codec.Sdo(
        SdoKind.ABORT, index, sub, abort_code=abort
    )


def test_sdo_frames_are_the_cia301_bytes() -> None:
    assert bytes(codec.encode_sdo_upload_request(5, 0x6041, 0).data) == bytes.fromhex(
        "4041600000000000"
    )
    assert bytes(codec.encode_sdo_download_request(5, 0x6060, 0, b"\x0a").data) == bytes.fromhex(
        "2f6060000a000000"
    )
    assert bytes(codec.encode_sdo_download_request(5, 0x1017, 0, b"\x64\x00").data) == (
        bytes.fromhex("2b17100064000000")
    )
    with pytest.raises(ValueError, match=r"1\.\.4 bytes"):
        codec.encode_sdo_download_request(5, 0x1008, 0, b"too long")
    assert "Object does not exist" in codec.abort_text(0x06020000)


DECODERS = [
    lambda data: codec.decode_rpdo1(0x201, data),
    lambda data: codec.decode_rpdo2(0x301, data),
    lambda data: codec.decode_tpdo1(0x181, data),
    lambda data: codec.decode_tpdo2(0x281, data),
    lambda data: codec.decode_emcy(0x81, data),
    lambda data: codec.decode_heartbeat(0x701, data),
    codec.decode_nmt,
    codec.decode_sync,
    lambda data: codec.decode_sdo_request(0x601, data),
    lambda data: codec.decode_sdo_response(0x581, data),
]


@pytest.mark.parametrize("decode", DECODERS)
@given(data=st.binary(max_size=64))
def test_decoders_decode_or_reject_any_bytes(decode, data: bytes) -> None:
    try:
        decode(bytearray(data))
    except Cia402FrameError as exc:
        assert exc.reason and str(exc).startswith("frame 0x")


def test_decoders_reject_undefined_values() -> None:
    with pytest.raises(Cia402FrameError, match="mode of operation"):
        codec.decode_rpdo1(0x201, struct.pack("<Hhb", 0x0F, 0, 3))
    with pytest.raises(Cia402FrameError, match="statusword pattern"):
        codec.decode_tpdo1(0x181, struct.pack("<Hib", 0x0001, 0, MODE_CST))
    with pytest.raises(Cia402FrameError, match="heartbeat state"):
        codec.decode_heartbeat(0x701, b"\x06")
    with pytest.raises(Cia402FrameError, match="NMT command"):
        codec.decode_nmt(b"\x03\x01")
    with pytest.raises(Cia402FrameError, match="SYNC counter"):
        codec.decode_sync(b"\x00")
    with pytest.raises(Cia402FrameError, match="TPDO2 length"):
        codec.decode_tpdo2(0x281, b"\x00" * 5)


@pytest.mark.parametrize(
    ("code", "words", "register"),
    [
        (0x8130, "heartbeat", 0x11),
        (0x8250, "RPDO timeout", 0x11),
        (0x2310, "overcurrent", 0x03),
        (0x3210, "overvoltage", 0x05),
        (0x4310, "overtemperature", 0x09),
        (0x7305, "encoder", 0x01),
        (0x8611, "following error", 0x21),
        (0x5123, "device hardware", 0x01),
        (0xFF42, "device-specific", 0x01),
    ],
)
def test_emcy_texts_and_error_registers(code: int, words: str, register: int) -> None:
    assert codec.emcy_text(code).startswith(f"EMCY 0x{code:04X}: ")
    assert words in codec.emcy_text(code)
    assert codec.error_register(code) == register
    assert codec.error_register(0) == 0


# -- the 402 power state machine -------------------------------------------------------------


def test_statuswords_encode_and_decode_every_state() -> None:
    for state in State:
        for hold in (False, True):
            word = encode_statusword(state, hold)
            assert decode_statusword(word) is state
            assert bool(word & STATUS_HOLD) is hold
    # the 402 examples: 0x0250 switch on disabled, 0x0231 ready, 0x0233 on, 0x0237 enabled
    assert [decode_statusword(w) for w in (0x0250, 0x0231, 0x0233, 0x0237, 0x0217, 0x0218)] == [
        State.SWITCH_ON_DISABLED,
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
        State.QUICK_STOP_ACTIVE,
        State.FAULT,
    ]
    assert decode_statusword(0x0001) is None and decode_statusword(0x0003) is None


def test_controlword_commands() -> None:
    assert decode_command(0x06) is Command.SHUTDOWN
    assert decode_command(0x07) is Command.SWITCH_ON
    assert decode_command(0x0F) is Command.ENABLE_OPERATION
    assert decode_command(0x00) is Command.DISABLE_VOLTAGE
    assert decode_command(0x00 | CONTROL_RELEASE_HOLD) is Command.DISABLE_VOLTAGE
    assert decode_command(0x0B) is Command.QUICK_STOP
    assert decode_command(0x80) is None  # fault reset is an edge, not a level command
    assert decode_command(0x8F) is None


EXPECTED_TRANSITIONS = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): State.SWITCHED_ON,
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,
    (State.SWITCHED_ON, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,
    (State.SWITCHED_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,
    (State.OPERATION_ENABLED, Command.SWITCH_ON): State.SWITCHED_ON,
    (State.OPERATION_ENABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,
    (State.OPERATION_ENABLED, Command.QUICK_STOP): State.QUICK_STOP_ACTIVE,
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,
    (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,
}


def test_every_transition_of_the_402_machine() -> None:
    for state in State:
        for command in [*Command, None]:
            expected = EXPECTED_TRANSITIONS.get((state, command), state)
            assert next_state(state, command) is expected, (state, command)


def test_drive_states_seen_by_the_host() -> None:
    assert drive_state(State.OPERATION_ENABLED, MODE_CST) is DriveState.ENABLED
    assert drive_state(State.OPERATION_ENABLED, MODE_CSP) is DriveState.HOLDING
    assert drive_state(State.SWITCHED_ON) is DriveState.READY
    assert drive_state(State.SWITCHED_ON, hold=True) is DriveState.HOLDING
    assert drive_state(State.QUICK_STOP_ACTIVE) is DriveState.HOLDING
    assert drive_state(State.SWITCH_ON_DISABLED) is DriveState.DISABLED
    assert drive_state(State.FAULT, hold=True) is DriveState.FAULT
    assert drive_state(State.FAULT_REACTION_ACTIVE) is DriveState.FAULT
    assert drive_state(None) is DriveState.UNKNOWN


# -- host driver on its own: scaling, signs, frames ----------------------------------------


def host(**overrides) -> Cia402Driver:
    """A driver whose SYNCs go out at time 0 (the frames below are received after)."""
    config = drives_config(**overrides)
    driver = Cia402Driver(config, config.scalings([RADIUS] * len(config.nodes)))
    driver.clock = lambda: 0.0
    return driver


def test_driver_basics_and_config_errors() -> None:
    driver = host()
    assert driver.timing is Timing.SYNC and driver.n == 3
    assert [m.arbitration_id for m in driver.cycle_start()] == [0x80, 0x77F]  # + heartbeat
    assert [m.arbitration_id for m in driver.cycle_start()] == [0x80]  # not due yet
    odrive = parse_drives({"protocol": "odrive", "nodes": [1]})
    with pytest.raises(ValueError, match="protocol cia402"):
        Cia402Driver(odrive, odrive.scalings([RADIUS]))
    with pytest.raises(ValueError, match="2 scalings for 3 drives"):
        Cia402Driver(drives_config(), drives_config().scalings([RADIUS] * 3)[:2])


def test_torque_commands_scale_round_and_follow_the_direction() -> None:
    driver = host()
    forces = [-100.0, -100.0, 33.3]
    frames = driver.commands(forces)
    assert [f.arbitration_id for f in frames] == [0x201, 0x202, 0x203]
    decoded = [codec.decode_rpdo1(f.arbitration_id, f.data) for f in frames]
    # -100 N along +l at r = 0.05 m, gear 10: -0.5 N·m = -250 per mille of 2 N·m
    assert decoded == [(0x0F, -250, MODE_CST), (0x0F, 250, MODE_CST), (0x0F, 83, MODE_CST)]
    for i, (_, torque, _) in enumerate(decoded):
        assert abs(torque - permille(driver, i, forces[i])) <= 0.5
    assert all(not f.is_extended_id for f in frames)
    assert driver.commands(np.array([0.0, 1e-3, -1e-3])) and driver.torque_limited == [0, 0, 0]


def test_torque_is_clamped_to_the_max_torque_and_counted() -> None:
    driver = host()
    frames = driver.commands([1e9, 1e9, -1e300])
    torques = [codec.decode_rpdo1(f.arbitration_id, f.data)[1] for f in frames]
    assert torques == [3000, -3000, -3000]  # 0x6072 default 3000 per mille; cable 1 reversed
    assert driver.torque_limited == [1, 1, 1]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_force_raises_frame_error(bad: float) -> None:
    driver = host()
    with pytest.raises(FrameError, match="cable 1 \\(node 2\\) is not finite"):
        driver.commands([0.0, bad, 0.0])
    with pytest.raises(FrameError, match="2 forces for 3"):
        driver.commands([0.0, 0.0])


def tpdos(node: int, statusword: int, position: int, velocity: int, mode: int = MODE_CST):
    return codec.encode_tpdo1(node, statusword, position, mode), codec.encode_tpdo2(node, velocity)


def test_feedback_scales_counts_with_gear_and_direction() -> None:
    driver = host()
    driver.cycle_start()
    enabled = encode_statusword(State.OPERATION_ENABLED)
    counts_per_metre = 4096 * 10 / (2 * math.pi * RADIUS)
    for node in (1, 2):
        first, second = tpdos(node, enabled, 40960, -20480)
        assert driver.receive(first, 1.0) is None
        assert driver.receive(second, 1.25) == node - 1
    one, two = driver.feedback[0], driver.feedback[1]
    # 40960 counts = 1 drum turn = 2 pi r of cable; cable 2 has direction -1
    assert one.length == pytest.approx(1.0 + 2 * math.pi * RADIUS)
    assert two.length == pytest.approx(2.0 - 2 * math.pi * RADIUS)
    assert one.rate == pytest.approx(-20480 / counts_per_metre)
    assert two.rate == pytest.approx(20480 / counts_per_metre)
    assert (one.stamp, one.count) == (1.25, 1)
    assert driver.status[0].state is DriveState.ENABLED
    assert driver.counters.accepted == 4


def test_feedback_is_complete_only_with_both_tpdos_of_one_sync() -> None:
    driver = host()
    enabled = encode_statusword(State.OPERATION_ENABLED)
    driver.cycle_start()
    first, second = tpdos(1, enabled, 100, 5)
    assert driver.receive(first, 0.0) is None
    driver.cycle_start()  # the next SYNC went out before the TPDO2 of the last one came
    assert driver.receive(second, 0.001) is None  # its TPDO1 was of the previous SYNC
    assert driver.feedback[0].count == 0
    first, second = tpdos(1, enabled, 200, 6)
    assert driver.receive(first, 0.002) == 0  # both TPDOs of this SYNC
    assert driver.receive(second, 0.004) is None  # a duplicate pairs with nothing
    assert driver.counters.rejected["TPDO after the sample was complete"] == 1
    assert driver.feedback[0].count == 1
    assert driver.position[0] == 200


def test_an_answer_received_before_the_latest_sync_is_not_its_answer() -> None:
    """The loop read the answers to the last SYNC only after the next went out (held up,
    or a thread that hands frames over late): received before that SYNC, they are
    dropped, not taken as its sample (a period old) nor as a second answer to it."""
    driver = host()
    enabled = encode_statusword(State.OPERATION_ENABLED)
    driver.clock = lambda: 1.0
    driver.cycle_start()
    driver.clock = lambda: 1.01
    driver.cycle_start()  # the next SYNC, before the answers to the first were read
    late, answer = tpdos(1, enabled, 100, 5), tpdos(1, enabled, 200, 6)
    assert [driver.receive(frame, 1.002) for frame in late] == [None, None]
    assert driver.counters.rejected["TPDO received before the latest SYNC"] == 2
    assert [driver.receive(frame, 1.012) for frame in answer] == [None, 0]
    assert driver.position[0] == 200 and driver.feedback[0].count == 1
    assert math.isnan(driver.feedback[0].second)  # no second answer
    assert driver.feedback[0].latched == 1.01


def test_an_answer_that_arrived_before_the_latest_sync_is_an_earlier_sync_s() -> None:
    """A frame's arrival is never earlier than the frame (its own stamp, or when the loop
    was handed it): an answer that arrived before the latest SYNC went out, however near
    it, answers an earlier SYNC, read late.  Taken as the latest one's, a drive answering
    a period late (a simulator's thread held up) put its length a period back, and four
    such drives braked a flight on implausible feedback."""
    driver = host()
    enabled = encode_statusword(State.OPERATION_ENABLED)
    driver.clock = lambda: 1.0
    driver.cycle_start()
    driver.clock = lambda: 1.01
    driver.cycle_start()
    late, answer = tpdos(1, enabled, 100, 5), tpdos(1, enabled, 200, 6)
    assert driver.receive(late[0], 1.0099) is None  # 0.1 ms before the latest SYNC
    assert driver.counters.rejected["TPDO received before the latest SYNC"] == 1
    assert [driver.receive(frame, 1.0101) for frame in answer] == [None, 0]
    assert driver.position[0] == 200 and driver.feedback[0].latched == 1.01


def test_a_second_answer_to_one_sync_is_dropped_and_its_length_recorded() -> None:
    """Another node's TPDOs of node 1 (or a late answer) to the same SYNC, after the
    sample or within it: the length of the second answer is recorded beside the first's
    (the pair that disagrees most, until the daemon takes it), whichever came first."""
    driver = host()
    enabled = encode_statusword(State.OPERATION_ENABLED)
    feedback, scaling = driver.feedback[0], driver.scalings[0]
    assert math.isnan(feedback.first) and math.isnan(feedback.second)
    driver.cycle_start()
    real, late = tpdos(1, enabled, 1000, 0), tpdos(1, enabled, 1010, 0)
    forged = tpdos(1, enabled, 90000, 0)
    assert [driver.receive(frame, 0.0) for frame in real] == [None, 0]
    assert [driver.receive(frame, 0.001) for frame in late + forged] == [None] * 4
    assert driver.counters.rejected["TPDO after the sample was complete"] == 4
    assert (driver.position[0], feedback.count) == (1000, 1)
    assert feedback.length == scaling.length(1000)
    assert (feedback.first, feedback.second) == (scaling.length(1000), scaling.length(90000))
    feedback.first = feedback.second = math.nan  # taken
    driver.cycle_start()  # the forged TPDO1 first, the real one within the same sample
    assert driver.receive(forged[0], 0.002) is None
    assert driver.receive(real[0], 0.002) is None  # it replaces the forged one
    assert driver.receive(forged[1], 0.003) == 0
    assert driver.receive(real[1], 0.003) is None
    assert driver.position[0] == 1000
    assert (feedback.first, feedback.second) == (scaling.length(90000), scaling.length(1000))


def test_emcy_heartbeat_and_fault_texts() -> None:
    driver = host()
    beat = codec.encode_heartbeat(2, NmtState.OPERATIONAL)
    assert driver.receive(beat, 3.5) is None
    assert driver.status[1].heartbeat_stamp == 3.5 and driver.nmt_state[1] is NmtState.OPERATIONAL
    driver.receive(codec.encode_emcy(2, 0x8611, 0x21), 4.0)
    status = driver.status[1]
    assert status.state is DriveState.FAULT and status.fault_code == 0x8611
    assert status.fault == "EMCY 0x8611: following error (error register 0x21)"
    driver.receive(codec.encode_emcy(2, 0, 0), 4.1)
    assert (status.fault, status.fault_code) == (None, 0)
    fault = encode_statusword(State.FAULT)
    driver.receive(codec.encode_tpdo1(2, fault, 0, MODE_CST), 4.2)
    assert status.state is DriveState.FAULT and "statusword reports FAULT" in status.fault


def _heartbeat_lost_after(silence: float) -> str:
    """The fault a drive's "heartbeat lost" EMCY (0x8130) leaves when this host ran its
    cycle every 2 ms for a second, then sent nothing for `silence` s, then one more cycle."""
    driver, now = host(), 0.0
    driver.clock = lambda: now
    while now < 1.0:
        driver.cycle_start()
        now += 0.002
    now += silence
    driver.cycle_start()
    driver.receive(codec.encode_emcy(2, codec.HEARTBEAT_LOST, 0x11), now + 0.0005)
    assert driver.status[1].fault_code == codec.HEARTBEAT_LOST
    return driver.status[1].fault


def test_a_lost_heartbeat_says_whether_this_host_was_held_up() -> None:
    """EMCY 0x8130 says the drive heard no host heartbeat for its consumer time; the
    driver's own record of the heartbeats it sent tells a held-up host (the drive was right
    to stop) from one whose heartbeats went out and were not heard (the bus or the drive)."""
    period, consumer = drives_config().host_heartbeat()
    on_time = _heartbeat_lost_after(0.0)
    assert on_time.startswith("EMCY 0x8130: life guard or heartbeat error (error register 0x11)")
    apart = float(re.search(r"at most ([\d.]+) ms apart", on_time)[1])
    assert apart == pytest.approx(period * 1e3, abs=2.0)
    assert "the drive did not hear them" in on_time and f"{consumer * 1e3:g} ms" in on_time
    held = _heartbeat_lost_after(consumer + 0.02)
    silent = float(re.search(r"sent no heartbeat for ([\d.]+) ms", held)[1])
    assert silent == pytest.approx((consumer + 0.02) * 1e3, abs=period * 1e3 + 2.0)
    assert held.endswith("it was held up")
    short = _heartbeat_lost_after(consumer / 2)  # a stall, shorter than the consumer time
    assert "the drive did not hear them" in short


def test_an_emcy_stays_a_fault_while_the_statusword_looks_healthy() -> None:
    """An EMCY (even one forged on the bus) is a fault until an error-reset EMCY: the
    next healthy statusword does not hide it before the daemon's safety check runs."""
    driver = host()
    status = driver.status[1]
    enabled = encode_statusword(State.OPERATION_ENABLED)
    driver.receive(codec.encode_tpdo1(2, enabled, 0, MODE_CST), 1.0)
    assert status.state is not DriveState.FAULT
    driver.receive(codec.encode_emcy(2, 0x2310, 0x03), 1.1)
    driver.receive(codec.encode_tpdo1(2, enabled, 0, MODE_CST), 1.2)
    assert status.state is DriveState.FAULT and status.fault_code == 0x2310
    driver.receive(codec.encode_emcy(2, 0, 0), 1.3)
    driver.receive(codec.encode_tpdo1(2, enabled, 0, MODE_CST), 1.4)
    assert status.state is not DriveState.FAULT and status.fault is None


HOSTILE = [
    (0x181, b"\x00" * 6, "TPDO1 length"),
    (0x181, b"\x00" * 8, "TPDO1 length"),
    (0x181, struct.pack("<Hib", 0x0001, 0, MODE_CST), "statusword pattern"),
    (0x281, b"\x00" * 3, "TPDO2 length"),
    (0x81, b"\x00" * 7, "EMCY length"),
    (0x701, b"", "heartbeat length"),
    (0x701, b"\x05\x00", "heartbeat length"),
    (0x701, b"\x42", "heartbeat state"),
]


@pytest.mark.parametrize(("can_id", "data", "reason"), HOSTILE)
def test_malformed_frames_are_counted_and_never_acted_on(
    can_id: int, data: bytes, reason: str
) -> None:
    driver = host()
    driver.cycle_start()
    before = (repr(driver.status), repr(driver.feedback), driver.position, driver.nmt_state)
    assert driver.receive(codec.message(can_id, data), 1.0) is None
    assert driver.counters.rejected == {reason: 1}
    assert driver.counters.accepted == 0
    assert (repr(driver.status), repr(driver.feedback), driver.position, driver.nmt_state) == before


def test_remote_extended_error_and_foreign_frames() -> None:
    driver = host()
    remote = can.Message(arbitration_id=0x181, is_remote_frame=True, is_extended_id=False)
    assert driver.receive(remote, 0.0) is None
    assert driver.counters.rejected == {"remote frame": 1}
    for frame in (
        can.Message(arbitration_id=0x181, data=b"\x37\x02" + b"\x00" * 5, is_extended_id=True),
        can.Message(arbitration_id=0x181, is_error_frame=True, is_extended_id=False),
        codec.message(0x184, b"\x37\x02" + b"\x00" * 5),  # node 4 is not ours
        codec.message(0x581, b"\x00" * 8),  # SDO answers are for the sequences
        codec.message(0x201, b"\x00" * 5),  # our own RPDO, looped back
        codec.message(0x80, b""),  # SYNC
    ):
        assert driver.receive(frame, 0.0) is None
    assert driver.counters.rejected_total == 1 and driver.counters.accepted == 0


frames_strategy = st.builds(
    lambda can_id, data, ext, rtr, fd: can.Message(
        arbitration_id=can_id,
        data=b"" if rtr else data,
        is_extended_id=ext,
        is_remote_frame=rtr,
        is_fd=fd,
        dlc=len(data),
    ),
    st.one_of(
        st.sampled_from([0x81, 0x181, 0x281, 0x701, 0x82, 0x182, 0x282, 0x702, 0x80, 0x0]),
        st.integers(0, 0x1FFFFFFF),
    ),
    st.binary(max_size=64),
    st.booleans(),
    st.booleans(),
    st.booleans(),
)


@given(st.lists(frames_strategy, max_size=40))
def test_garbage_floods_never_crash_the_host(frames: list[can.Message]) -> None:
    driver = host()
    driver.cycle_start()
    for frame in frames:
        index = driver.receive(frame, 0.5)
        assert index is None or 0 <= index < driver.n
    assert driver.counters.accepted + driver.counters.rejected_total <= len(frames)


@given(st.lists(st.sampled_from(HOSTILE), max_size=60))
def test_malformed_floods_change_nothing(hostile: list[tuple[int, bytes, str]]) -> None:
    driver = host()
    for can_id, data, _ in hostile:
        assert driver.receive(codec.message(can_id, data), 2.0) is None
    assert driver.counters.rejected_total == len(hostile) and driver.counters.accepted == 0
    assert all(s.state is DriveState.UNKNOWN and s.fault is None for s in driver.status)
    assert all(f.count == 0 for f in driver.feedback)


def test_brake_frames_position_hold() -> None:
    driver = host()
    driver.position[2] = 777  # cable 2 last reported 777 increments: a frame, not trusted
    frames = driver.brake([1.5, 2.0, math.nan], BrakeMode.POSITION_HOLD)
    assert [f.arbitration_id for f in frames] == [0x301, 0x302, 0x203]
    decoded = [codec.decode_rpdo2(f.arbitration_id, f.data) for f in frames[:2]]
    expected_1 = round(driver.scalings[0].position(1.5))
    assert decoded == [(0x0F, expected_1, MODE_CSP), (0x0F, 0, MODE_CSP)]
    # no trusted length for cable 2: power stage off, never a hold at a reported position
    assert codec.decode_rpdo1(0x203, frames[2].data) == (0x07, 0, MODE_CST)
    again = driver.keepalive()
    assert [bytes(f.data) for f in again[:3]] == [bytes(f.data) for f in frames]
    # then each drive is asked by SDO whether it holds (drivers.cia402.hold_check)
    asked = [codec.decode_sdo_request(f.arbitration_id, f.data) for f in again[3:]]
    assert [f.arbitration_id for f in again[3:]] == [0x601, 0x602, 0x603]
    assert {(sdo.kind, sdo.index) for sdo in asked} == {(codec.SdoKind.UPLOAD, 0x6041)}
    driver.commands([0.0] * 3)
    assert driver.keepalive() == []


def test_brake_never_raises_and_falls_back_safely() -> None:
    driver = host()
    # never heard from, no length: power stage off (brake where fitted) via disable operation
    frames = driver.brake([math.inf], BrakeMode.POSITION_HOLD)
    assert [codec.decode_rpdo1(f.arbitration_id, f.data) for f in frames] == [
        (0x07, 0, MODE_CST)
    ] * 3
    # a holding brake asked of drives without one: position hold instead
    frames = driver.brake([1.0, 2.0, 3.0], BrakeMode.HOLDING_BRAKE)
    assert [f.arbitration_id for f in frames] == [0x301, 0x302, 0x303]


def test_brake_frames_holding_brake_and_disable() -> None:
    driver = host(brake="holding_brake", has_holding_brake=True)
    frames = driver.brake([1.0, 2.0, 3.0], BrakeMode.HOLDING_BRAKE)
    assert [codec.decode_rpdo1(f.arbitration_id, f.data) for f in frames] == [
        (Command.SWITCH_ON.value, 0, MODE_CST)  # "disable operation" from OPERATION ENABLED
    ] * 3
    frames = driver.disable()
    word = Command.DISABLE_VOLTAGE.value | CONTROL_RELEASE_HOLD
    assert [codec.decode_rpdo1(f.arbitration_id, f.data) for f in frames] == [
        (word, 0, MODE_CST)
    ] * 3
    assert len(driver.keepalive()) == 3


# -- host <-> device round trips -----------------------------------------------------------


def test_start_configures_every_drive_through_sdo() -> None:
    driver, devices, link = make_bus()
    config = driver.config
    for device in devices:
        assert device.nmt_state is NmtState.OPERATIONAL
        assert device.state is State.SWITCHED_ON
        assert device.heartbeat_period == config.heartbeat_period
        assert device.rpdo_deadlines == {}  # off: the consumer heartbeat is the watchdog
        assert device.brake_reaction is BrakeMode.POSITION_HOLD
        assert device.consumers == {127: config.host_heartbeat()[1]}  # the host's heartbeat
        assert device.values[(0x6007, 0)] == 3 and device.values[(0x605A, 0)] == 6
        assert device.actuation is Actuation.POSITION  # power-on hold: no brake fitted
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3
    assert all(s.heartbeat_stamp > 0 for s in driver.status)
    assert driver.nmt_state == [NmtState.OPERATIONAL] * 3
    ids = {m.arbitration_id for m in link.sent}
    # NMT, SDO and the host's heartbeat (its consumers stay fed through the start-up)
    assert ids == {0x000, 0x77F} | {0x600 + n for n in (1, 2, 3)}
    writes = [
        bytes(m.data) for m in link.sent if m.arbitration_id == 0x601 and m.data[0] & 0xE0 == 0x20
    ]
    assert bytes.fromhex("2b17100064000000") in writes  # 0x1017 = 100 ms
    assert bytes.fromhex("2b00140500000000") in writes  # 0x1400:05 = 0 (no deadline)
    assert bytes.fromhex("2b01140500000000") in writes  # 0x1401:05 = 0


def test_start_with_holding_brakes_ends_ready_with_brakes_on() -> None:
    driver, devices, _ = make_bus(brake="holding_brake", has_holding_brake=True)
    assert [s.state for s in driver.status] == [DriveState.READY] * 3
    for device in devices:
        assert device.actuation is Actuation.OFF and device.brake_engaged
        assert device.brake_reaction is BrakeMode.HOLDING_BRAKE


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.values.__setitem__((0x6076, 0), 2500), "rated torque 0x6076 is 2.5"),
        (lambda d: d.values.__setitem__((0x1000, 0), 0x191), "is no CiA 402 drive"),
        (
            lambda d: setattr(d, "_pdo_write", lambda *a: 0x06040041),
            "0x1400:01.*aborted: 0x06040041 Object cannot be mapped to the PDO",
        ),
    ],
)
def test_start_refuses_a_drive_that_differs(change, message: str) -> None:
    driver, devices, link = make_bus(started=False)
    change(devices[1])
    with pytest.raises(DriverError, match=f"node 2: .*{message}"):
        link.run(driver.start(link, lambda: link.t))


def test_start_names_a_silent_node() -> None:
    driver, _, link = make_bus(started=False)
    link.mute.add(3)
    with pytest.raises(DriverError, match="node 3: SDO read 0x6041:00"):
        link.run(driver.start(link, lambda: link.t))


@pytest.mark.parametrize("layout", ["default", "compact"])
def test_start_takes_over_enabled_drives_without_a_torque_step(layout: str) -> None:
    """A restarted host finds its drives enabled (two in torque, one holding): it reads
    state, mode and position first, never sends NMT pre-operational to them, and keeps
    sending what they do; the forces never change (with the compact layout's shared
    torque RPDO too: every drive's torque is read before it goes out)."""
    lengths = [1.5, 2.5, 0.75]
    profile = compact_profile() if layout == "compact" else {}
    driver, devices, link = make_bus(lengths, profile=profile)
    link.run(driver.enable(link, lengths, [0.0] * 3))
    link.cycle([-100.0, -60.0, -20.0])
    link.cycle([-100.0, -60.0, -20.0])
    devices[2].on_frame(codec.encode_rpdo2(3, 0x0F, devices[2]._position(), MODE_CSP), link.t)
    before = [(d.actuation, d.force, d.target_length) for d in devices]
    config = driver.config
    again = Cia402Driver(config, config.scalings([RADIUS] * 3))
    link.driver, link.sent = again, []
    forces = []
    link.every_tick = lambda: forces.append([d.force for d in devices])
    link.run(again.start(link, lambda: link.t))
    assert all(m.arbitration_id != 0 or m.data[0] != 0x80 for m in link.sent)  # no pre-op
    assert [(d.actuation, d.force) for d in devices] == [(a, f) for a, f, _ in before]
    assert all(f == forces[0] for f in forces)
    assert devices[2].target_length == pytest.approx(before[2][2], abs=1e-5)
    assert all(d.state is State.OPERATION_ENABLED for d in devices)
    assert [s.state for s in again.status] == [DriveState.ENABLED] * 2 + [DriveState.HOLDING]
    # it goes on feeding their deadlines (compact: one torque frame for both)
    assert len(again.keepalive()) == (2 if layout == "compact" else 3)


def test_an_unexpected_mode_display_is_a_reported_fault_not_a_dropped_frame() -> None:
    driver = host()
    driver.cycle_start()
    first, second = tpdos(1, encode_statusword(State.OPERATION_ENABLED), 100, 5, mode=3)
    driver.receive(first, 0.0)
    assert driver.receive(second, 0.0) == 0  # the feedback counts
    assert driver.status[0].state is DriveState.FAULT
    assert "mode of operation display 3" in driver.status[0].fault
    assert codec.decode_rpdo1(0x201, struct.pack("<Hhb", 0x0F, 5, 0)) == (0x0F, 5, 0)


def test_start_waits_for_operational_heartbeats() -> None:
    driver, _, link = make_bus(started=False)
    link.drop = lambda message: message.arbitration_id == 0x701  # node 1's heartbeats lost
    with pytest.raises(
        DriverError, match=r"no operational heartbeat from node\(s\) 1 within 0.35 s$"
    ):
        link.run(driver.start(link, lambda: link.t))


def test_start_counts_heartbeats_received_between_its_waits() -> None:
    """A heartbeat that reaches receive() while start() is between two waits (the
    daemon's loop ran the bus reader first) counts: start() waits for heartbeats in short
    steps, so that its own heartbeat keeps the drives' consumers fed."""
    driver, _, link = make_bus(started=False)

    def straight_to_receive(message: can.Message) -> bool:
        """Heartbeats reach receive() as the drives send them, never a wait's match."""
        if message.arbitration_id & 0x780 != 0x700:
            return False
        driver.receive(message, link.t)
        return True

    link.drop = straight_to_receive
    link.run(driver.start(link, lambda: link.t))
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3


def test_start_names_a_drive_that_ignores_its_controlword() -> None:
    driver, devices, link = make_bus(started=False)
    devices[0]._control = lambda *args, **kwargs: []  # obeys nothing
    with pytest.raises(
        DriverError, match=r"node 1: controlword SHUTDOWN did not reach READY_TO_SWITCH_ON"
    ):
        link.run(driver.start(link, lambda: link.t))
    driver, devices, link = make_bus(started=False)
    devices[2]._live[(0x6041, 0)] = lambda: 0x0001  # an undefined 402 pattern
    with pytest.raises(DriverError, match="node 3: statusword 0x0001 is no CiA 402 state"):
        link.run(driver.start(link, lambda: link.t))


def test_enable_names_drives_that_do_not_enable_or_fault() -> None:
    driver, _, link = make_bus()
    link.drop = lambda message: message.arbitration_id == 0x183  # node 3's TPDO1 lost
    with pytest.raises(DriverError, match=r"node\(s\) 3 did not reach OPERATION ENABLED"):
        link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    driver, devices, link = make_bus()
    injected = []

    def encoder_fails(message: can.Message) -> bool:
        if message.arbitration_id == 0x182 and not injected:
            injected.extend(devices[1].inject_fault(0x7305, "encoder lost"))
            link.queue.extend(injected)
            return True
        return False

    link.drop = encoder_fails
    with pytest.raises(DriverError, match=r"enable: node\(s\) 2 went to FAULT"):
        link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    assert driver.status[1].fault.startswith("EMCY 0x7305: position encoder fault")
    with pytest.raises(DriverError, match="enable needs 3 cable lengths"):
        link.run(driver.enable(link, [1.5], [0.0] * 3))
    with pytest.raises(DriverError, match="cable 0 length nan m"):
        link.run(driver.enable(link, [math.nan, 1.5, 1.5], [0.0] * 3))


def test_enable_holds_then_torque_commands_reach_the_drives() -> None:
    lengths = [1.5, 2.5, 0.75]
    driver, devices, link = make_bus(lengths)
    link.run(driver.enable(link, lengths, [0.0] * 3))
    for device, length in zip(devices, lengths, strict=True):
        assert device.state is State.OPERATION_ENABLED and device.mode == MODE_CSP
        assert device.actuation is Actuation.POSITION and not device.brake_engaged
        assert device.target_length == pytest.approx(length, abs=1e-5)
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3
    forces = [-120.0, -80.0, -40.0]
    for device, rate in zip(devices, [0.01, -0.02, 0.0], strict=True):
        device.measure(device.length, rate)
    done = link.cycle(forces)
    assert sorted(i for i in done if i is not None) == [0, 1, 2]
    for i, device in enumerate(devices):
        assert device.actuation is Actuation.TORQUE and device.mode == MODE_CST
        # one per mille of 2 N·m at r/gear = 5 mm is 0.4 N
        assert device.force == pytest.approx(forces[i], abs=0.2)
        feedback = driver.feedback[i]
        assert feedback.length == pytest.approx(lengths[i], abs=1e-5)
        assert feedback.rate == pytest.approx(device.rate, abs=1e-4)
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3  # TPDOs before commands
    link.cycle(forces)
    assert [s.state for s in driver.status] == [DriveState.ENABLED] * 3


def test_enable_sends_no_sync_of_its_own_while_the_daemon_s_cycle_sends_them() -> None:
    """The enable's rounds ask for TPDOs by SYNC only where no cycle does: a second
    source between the cycle's SYNCs had each one's answers read after the other's
    (dropped as answers to a SYNC before), and every drive went stale in a slow guest.
    Alone (a test, a tool), it sends its own."""
    lengths = [1.5, 2.5, 0.75]
    driver, _, link = make_bus(lengths)
    cycle = {"next": link.t, "syncs": 0}

    def daemon_cycle() -> None:  # a 100 Hz cycle on the same bus
        if link.t >= cycle["next"] - 1e-9:
            cycle["next"] += 0.01
            cycle["syncs"] += 1
            for frame in driver.cycle_start():
                link.send(frame)

    link.every_tick = daemon_cycle
    for _ in range(50):  # the cycle runs before the enable, as the daemon's does
        link.advance(0.001)
        link.deliver()
    start, before = len(link.sent), cycle["syncs"]
    link.run(driver.enable(link, lengths, [0.0] * 3))
    link.every_tick = lambda: None
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3
    syncs = sum(m.arbitration_id == 0x80 for m in link.sent[start:])
    assert syncs == cycle["syncs"] - before > 0  # the cycle's, none of its own

    alone, _, link = make_bus(lengths)
    start = len(link.sent)
    link.run(alone.enable(link, lengths, [0.0] * 3))
    assert any(m.arbitration_id == 0x80 for m in link.sent[start:])


def test_cycles_keep_the_drives_fed_and_feedback_fresh() -> None:
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.deliver()  # the TPDO2s enable() did not wait for
    for k in range(200):  # 0.4 s at 500 Hz, far past the 50 ms RPDO deadline
        devices[0].measure(1.5 + 1e-4 * k, 0.05)
        assert sorted(i for i in link.cycle([-50.0] * 3) if i is not None) == [0, 1, 2]
        link.advance(0.002)
    assert all(
        d.state is State.OPERATION_ENABLED and d.actuation is Actuation.TORQUE for d in devices
    )
    assert driver.feedback[0].length == pytest.approx(1.5 + 1.99e-2, abs=1e-5)
    assert driver.counters.rejected_total == 0


@pytest.mark.parametrize("layout", ["default", "compact"])
def test_switching_between_hold_and_torque_never_lets_an_rpdo_deadline_expire(layout: str):
    """A drive times each RPDO apart (CiA 301 event timer 0x14xx:05), and the host sends
    the hold RPDO only in a hold, the torque RPDO only in torque control (compact: the
    control RPDO only on change).  Hold (enable), torque, hold (brake), torque, 0.2 s
    each at 500 Hz, four times the 50 ms watchdog_timeout: every drive of the project's
    EDS (which has the deadlines) stays OPERATION ENABLED throughout."""
    profile = compact_profile() if layout == "compact" else {}
    driver, devices, link = make_bus(profile=profile)
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    for phase in ("hold", "torque", "hold", "torque"):
        if phase == "hold" and driver.status[0].state is DriveState.ENABLED:
            for frame in driver.brake([f.length for f in driver.feedback], BrakeMode.POSITION_HOLD):
                link.send(frame)
        for _ in range(100):
            if phase == "hold":
                for frame in driver.keepalive():
                    link.send(frame)
                link.cycle()
            else:
                link.cycle([-50.0] * 3)
            link.advance(0.002)
            assert [(d.state, d.fault_text) for d in devices] == [
                (State.OPERATION_ENABLED, None)
            ] * 3, phase
        wanted = Actuation.POSITION if phase == "hold" else Actuation.TORQUE
        assert all(d.actuation is wanted for d in devices)


def test_brake_position_hold_round_trip() -> None:
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    for device, length in zip(devices, [1.4, 1.6, 1.7], strict=True):
        device.measure(length, 0.1)
    link.cycle()
    lengths = [f.length for f in driver.feedback]
    for frame in driver.brake(lengths, BrakeMode.POSITION_HOLD):
        link.send(frame)
    for device, length in zip(devices, [1.4, 1.6, 1.7], strict=True):
        assert device.actuation is Actuation.POSITION and device.mode == MODE_CSP
        assert device.target_length == pytest.approx(length, abs=1e-5)
    for _ in range(100):  # keepalive feeds the deadline while braked
        for frame in driver.keepalive():
            link.send(frame)
        link.cycle()
        link.advance(0.002)
    assert all(d.state is State.OPERATION_ENABLED for d in devices)
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3


def test_brake_holding_brake_round_trip_and_disable() -> None:
    # a patient consumer heartbeat: the host stays silent for 0.2 s below
    driver, devices, link = make_bus(
        brake="holding_brake", has_holding_brake=True, consumer_heartbeat_time=0.5
    )
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    assert all(d.actuation is Actuation.TORQUE and not d.brake_engaged for d in devices)
    for frame in driver.brake([1.5] * 3, BrakeMode.HOLDING_BRAKE):
        link.send(frame)
    for device in devices:
        assert device.state is State.SWITCHED_ON
        assert device.actuation is Actuation.OFF and device.brake_engaged
    link.advance(0.2)  # no deadline outside OPERATION ENABLED
    link.cycle()
    assert [s.state for s in driver.status] == [DriveState.READY] * 3
    for frame in driver.disable():
        link.send(frame)
    assert all(d.state is State.SWITCH_ON_DISABLED and d.brake_engaged for d in devices)


def drive_faults(devices: list[Cia402Drive], link: MemoryLink, code: int = 0x4310) -> None:
    """Every drive detects fault `code` (its EMCY to the host's queue)."""
    for device in devices:
        link.queue.extend(device.inject_fault(code, "drive fault"))


def test_a_drive_fault_brakes_and_resets_without_moving() -> None:
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    devices[1].measure(1.62, 0.3)
    drive_faults(devices, link)
    link.deliver()
    for device in devices:
        assert device.state is State.FAULT and device.fault_code == 0x4310
        assert device.actuation is Actuation.POSITION
    assert devices[1].target_length == 1.62  # held where it was when it faulted
    for status in driver.status:
        assert status.state is DriveState.FAULT and status.fault_code == 0x4310
        assert "drive overtemperature" in status.fault
    with pytest.raises(DriverError, match="node 1 is in FAULT \\(EMCY 0x4310: drive overtemp"):
        link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.run(driver.reset_faults(link))
    for device in devices:
        assert device.state is State.SWITCHED_ON and device.hold is BrakeMode.POSITION_HOLD
        assert device.actuation is Actuation.POSITION  # still holding, never moving
    assert devices[1].target_length == 1.62
    assert [(s.state, s.fault) for s in driver.status] == [(DriveState.HOLDING, None)] * 3
    link.run(driver.enable(link, [1.5, 1.62, 1.5], [0.0] * 3))
    assert all(d.state is State.OPERATION_ENABLED and d.hold is None for d in devices)


def test_keepalive_during_a_fault_reset_does_not_re_enable_the_drives() -> None:
    """The daemon's cycle keeps sending keepalive() while reset_faults runs: the repeated
    brake frames (enable operation, mode 8) must not push a drive the reset is stepping
    through SWITCH ON DISABLED -> READY -> SWITCHED ON on to OPERATION ENABLED."""
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    drive_faults(devices, link)  # every drive faults and holds by itself
    link.deliver()
    for frame in driver.brake([1.5] * 3, BrakeMode.POSITION_HOLD):
        link.send(frame)
    link.every_tick = lambda: [link.send(frame) for frame in driver.keepalive()]
    link.run(driver.reset_faults(link))
    for device in devices:
        assert device.state is State.SWITCHED_ON and device.actuation is Actuation.POSITION


def test_a_drive_fault_with_holding_brakes() -> None:
    driver, devices, link = make_bus(brake="holding_brake", has_holding_brake=True)
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    drive_faults(devices, link)
    link.deliver()
    assert all(d.actuation is Actuation.OFF and d.brake_engaged for d in devices)
    assert all(s.state is DriveState.FAULT for s in driver.status)
    link.run(driver.reset_faults(link))
    assert all(d.state is State.SWITCHED_ON and d.brake_engaged for d in devices)
    assert [s.state for s in driver.status] == [DriveState.HOLDING] * 3


def test_a_persistent_fault_survives_reset_until_its_cause_is_gone() -> None:
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    for frame in devices[2].inject_fault(0x4310, "power stage too hot", persistent=True):
        link.queue.append(frame)
    link.deliver()
    assert driver.status[2].fault == "EMCY 0x4310: drive overtemperature (error register 0x09)"
    with pytest.raises(DriverError, match=r"node 3: still in FAULT .*0x4310: drive overtemp"):
        link.run(driver.reset_faults(link))
    devices[2].clear_fault_cause()
    link.run(driver.reset_faults(link))
    assert devices[2].state is State.SWITCHED_ON and driver.status[2].fault is None


def test_quick_stop_holds_and_the_host_sees_holding() -> None:
    driver, devices, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    link.send(codec.encode_rpdo1(2, Command.QUICK_STOP.value, 0, MODE_CST))
    assert devices[1].state is State.QUICK_STOP_ACTIVE
    assert devices[1].actuation is Actuation.POSITION  # never a torque ramp to zero
    link.cycle([-60.0, -60.0, -60.0])
    assert driver.status[1].state is DriveState.HOLDING


def test_a_rebooted_drive_faults_until_started_again() -> None:
    driver, _, link = make_bus()
    link.send(codec.encode_nmt(NmtCommand.RESET_NODE, 2))
    link.deliver()
    assert driver.status[1].state is DriveState.FAULT
    assert "restarted" in driver.status[1].fault
    with pytest.raises(DriverError, match=r"node 2 is not started .*restarted"):
        link.run(driver.reset_faults(link))
    link.run(driver.start(link, lambda: link.t))
    assert driver.status[1].state is DriveState.HOLDING and driver.status[1].fault is None


def test_a_boot_up_heartbeat_from_an_operational_drive_stays_a_fault() -> None:
    """A boot-up heartbeat (even a forged one, the drive still operational and sending
    healthy statuswords) means the drive lost its configuration and position: a FAULT
    naming the node until start() runs again, not hidden by the next TPDO1."""
    driver, _, link = make_bus()
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-60.0] * 3)
    link.cycle([-60.0] * 3)
    assert driver.status[1].state is DriveState.ENABLED
    driver.receive(codec.encode_heartbeat(2, NmtState.BOOT_UP), link.t)
    for _ in range(3):  # the real drive goes on answering every SYNC
        link.cycle([-60.0] * 3)
    status = driver.status[1]
    assert status.state is DriveState.FAULT
    assert status.fault.startswith("node 2: the drive restarted (boot-up heartbeat")
    assert driver.status[0].state is DriveState.ENABLED
    with pytest.raises(DriverError, match=r"node 2 is not started .*restarted"):
        link.run(driver.reset_faults(link))


def test_heartbeats_keep_arriving_after_start() -> None:
    driver, _, link = make_bus()
    first = [s.heartbeat_stamp for s in driver.status]
    for _ in range(250):
        link.advance(0.001)
        link.deliver()
    assert all(
        s.heartbeat_stamp >= f + 0.2 - 1e-9 for s, f in zip(driver.status, first, strict=True)
    )
    assert driver.counters.rejected_total == 0


# -- a dead daemon (the consumer heartbeat is the drives' watchdog) -----------------

VENDOR_EDS = Path(__file__).resolve().parents[1] / "data" / "generic_servo_cia402.eds"


def vendor_bus() -> tuple[Cia402Driver, list[Cia402Drive], MemoryLink]:
    """Three strict simulated drives with the vendor EDS (no RPDO deadline 0x1400:05: the
    consumer heartbeat is their only watchdog), started by the host with its defaults."""
    config = drives_config(rated_torque=1.0, profile={"eds": str(VENDOR_EDS)})
    scalings = config.scalings([RADIUS] * 3)
    driver = Cia402Driver(config, scalings)
    devices = [
        Cia402Drive(node, s, config, eds=VENDOR_EDS)
        for node, s in zip(config.nodes, scalings, strict=True)
    ]
    for device in devices:
        device.measure(1.5, 0.0)
    link = MemoryLink(driver, devices)
    link.run(driver.start(link, lambda: link.t))
    return driver, devices, link


@pytest.mark.parametrize("eds", ["vendor", "project"])
def test_a_killed_daemon_leaves_the_drives_holding_within_twice_the_consumer_time(eds: str):
    """kill -9 of the daemon while it commands torque at 500 Hz: no goodbye frame, no
    heartbeat any more.  The drives (the vendor EDS has no RPDO deadline, the project's
    has them and the host turns them off) apply the last torque until their consumer
    heartbeat expires; the host set that to tens of ms (58 ms: watchdog_timeout after the
    heartbeat due next), so each drive holds (QUICK STOP ACTIVE, position) within twice
    that of the kill, and not before it: the heartbeat every 6 ms keeps it fed."""
    driver, devices, link = vendor_bus() if eds == "vendor" else make_bus()
    assert all(d.rpdo_deadlines == {} for d in devices)
    consumer = devices[0].consumers[127]
    assert consumer == 0.058 and all(d.consumers == {127: consumer} for d in devices)
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    for _ in range(100):  # 0.2 s of control at 500 Hz
        link.cycle([-60.0] * 3)
        link.advance(0.002)
        assert all(d.state is State.OPERATION_ENABLED for d in devices)
    assert all(d.actuation is Actuation.TORQUE for d in devices)
    killed, held = link.t, {}
    for _ in range(1000):  # the host is gone: only the drives tick
        link.advance(0.001)
        for device in devices:
            if device.state is State.QUICK_STOP_ACTIVE and device.node_id not in held:
                held[device.node_id] = link.t - killed
                assert device.actuation is Actuation.POSITION  # holds, never free-wheels
        if len(held) == len(devices):
            break
    assert sorted(held) == [1, 2, 3]
    assert all(delay <= 2 * consumer for delay in held.values()), held


def test_the_host_reads_max_torque_after_the_profiles_writes() -> None:
    """A profile that lowers the max torque 0x6072 gets its clamp: the host reads the
    limit after applying sdo_writes, not the drive's value from before them."""
    writes = [{"object": 0x6072, "value": 1500}]
    driver, devices, link = make_bus(profile={"sdo_writes": writes})
    assert all(d.values[(0x6072, 0)] == 1500 for d in devices)
    assert driver.max_torque == [1500] * 3
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.cycle([-1000.0] * 3)  # 4000 per mille of the rated torque asked
    assert driver.torque_limited == [1, 1, 1]
    assert all(abs(d.values[(0x6071, 0)]) == 1500 for d in devices)


@pytest.mark.parametrize(
    ("overrides", "problem"),
    [
        ({"consumer_heartbeat_time": 0.0025}, "0.0025 s is no whole number of milliseconds"),
        (
            {"host_heartbeat_period": 0.01, "consumer_heartbeat_time": 0.015},
            "consumer_heartbeat_time (0.015 s) must be at least twice host_heartbeat_period",
        ),
    ],
)
def test_host_heartbeat_settings_are_whole_ms_and_leave_a_margin(overrides, problem) -> None:
    with pytest.raises(ConfigError, match=re.escape(problem)):
        drives_config(**overrides)


def test_host_heartbeat_defaults_follow_the_control_rate() -> None:
    """Whole cycles of at least 5 ms; the consumer time is watchdog_timeout after the
    heartbeat due next (+ a period and a cycle)."""
    config = drives_config()
    assert config.host_heartbeat() == (0.006, 0.058)  # 500 Hz: every 3rd cycle
    assert config.host_heartbeat(1 / 300) == (0.007, 0.061)  # 300 Hz: every 2nd cycle
    assert config.host_heartbeat(0.03) == (0.03, 0.11)  # 33 Hz: every cycle
    assert drives_config(watchdog_timeout=0.02).host_heartbeat() == (0.006, 0.028)
    slow = drives_config(host_heartbeat_period=0.002, consumer_heartbeat_time=0.01)
    with pytest.raises(ValueError, match="consumer_heartbeat_time: 10 ms is less than twice"):
        slow.host_heartbeat(0.01)  # the heartbeat goes out at most once per 10 ms cycle


# -- the compact layout: one shared torque RPDO per bus -------------------------

TWO_BUS = Path(__file__).resolve().parents[2] / "config" / "reference8-cia402-2bus.yaml"
NODES = [1, 2, 3]  # drives_config's


def frames(messages: list[can.Message]) -> list[tuple[int, bytes]]:
    """(COB-ID, data) of `messages` but the host's heartbeat (its own pace, not a cycle's)."""
    heartbeat = 0x700 + 127
    return [(m.arbitration_id, bytes(m.data)) for m in messages if m.arbitration_id != heartbeat]


def compact_profile(**changes: object) -> dict:
    """drives.profile of config/reference8-cia402-2bus.yaml (the compact layout)."""
    profile = load_yaml(TWO_BUS)["drives"]["profile"]
    return {**profile, **changes}


def test_the_compact_layout_sends_one_torque_frame_and_the_controlword_on_change() -> None:
    driver, devices, link = make_bus(profile=compact_profile())
    for slot, device in enumerate(devices):  # each its own 2 bytes of RPDO1 at 0x201
        mapping = [device.values[(0x1600, k)] for k in range(1, 4)]
        assert mapping == [0x60710010 if k == slot else 0x00060010 for k in range(3)]
        assert device.values[(0x1400, 1)] == 0x201
    link.run(driver.enable(link, [1.5] * 3, [0.0] * 3))
    link.advance(0.001)
    link.sent.clear()
    forces = [10.0, -20.0, 30.0]
    assert sorted(link.cycle(forces)) == [0, 1, 2]  # position alone completes the sample
    torques = [round(permille(driver, i, f)) for i, f in enumerate(forces)]
    shared = codec.message(0x201, struct.pack("<hhh", *torques))
    control = [codec.message(0x400 + node, struct.pack("<Hb", 0x0F, MODE_CST)) for node in NODES]
    assert frames(link.sent[1:]) == frames([shared, *control])  # torque first, then mode 10
    assert [d.target_torque for d in devices] == torques
    assert all(d.actuation is Actuation.TORQUE for d in devices)
    link.advance(0.002)
    link.sent.clear()
    for device in devices:  # cable 0 pays out 1 mm in the 2 ms between two SYNCs
        device.measure(1.501 if device is devices[0] else 1.5, 0.0)
    link.cycle(forces)
    assert frames(link.sent[1:]) == frames([shared])  # no change: no control RPDO
    assert driver.feedback[0].rate == pytest.approx(0.5, abs=0.01)  # differentiated
    assert driver.feedback[1].rate == pytest.approx(0.0, abs=0.01)
    link.sent.clear()
    for frame in driver.brake([1.501, 1.5, 1.5], BrakeMode.POSITION_HOLD):
        link.send(frame)
    assert {m.arbitration_id for m in link.sent} == {0x300 + node for node in NODES}
    assert all(d.actuation is Actuation.POSITION for d in devices)
    link.sent.clear()
    link.cycle(forces)  # torque again: the controlword and mode go out again
    assert frames(link.sent[1:]) == frames([shared, *control])
    link.mute.add(1)  # silent: no position on SYNC, no sample (the daemon's stale check)
    counts = [fb.count for fb in driver.feedback]
    assert sorted(i for i in link.cycle(forces) if i is not None) == [1, 2]
    assert [fb.count - c for fb, c in zip(driver.feedback, counts, strict=True)] == [0, 1, 1]


def test_compact_layouts_the_eds_or_the_bus_refuse_are_named(tmp_path: Path) -> None:
    eds = str(no_dummies(tmp_path))
    torque = {"number": 1, "objects": [0x6071], "transmission_type": 255}
    hold = {"number": 2, "objects": [0x6040, 0x607A, 0x6060], "transmission_type": 255}
    control = {"number": 3, "objects": [0x6040, 0x6060], "transmission_type": 255}
    cases = [
        (
            {"profile": compact_profile(eds=eds)},
            r"profile.rpdo.0.shared: each drive skips the others' 16-bit 0x6071 with a dummy "
            r"entry, 0x0006 \(UNSIGNED16\) or 0x0003 \(INTEGER16\), which the EDS does not allow",
        ),
        (
            {"profile": compact_profile(eds=eds, rpdo=[{**torque, "objects": [6, 0x6071]}])},
            r"profile.rpdo.0.objects.0: dummy entry 0x0006 \(UNSIGNED16\) is not allowed by "
            r"the EDS \(\[DummyUsage\] Dummy0006 is not 1\)",
        ),
        (
            {
                "profile": compact_profile(),
                "nodes": [1, 2, 3, 4, 5],
                "direction": 1,
                "length_offset": 0.0,
            },
            r"profile.rpdo.0.objects: 10 bytes for the 5 drives of the bus \(2 each\): a PDO "
            "carries at most 8",
        ),
        (
            {"profile": compact_profile(rpdo=[{**torque, "cob_id": 0x200}, hold, control])},
            r"profile.rpdo.0.cob_id: nodes 1 and 2 both take byte 0 of COB-ID 0x200 "
            r"\(0x6071\): two drives claiming the same bytes",
        ),
        (
            {"profile": compact_profile(rpdo=[torque, hold, {**control, "cob_id": 0x182}])},
            r"profile.rpdo.2.cob_id: COB-ID 0x182 of node 1's RPDO3 is also node 2's TPDO1's",
        ),
        (
            {"profile": compact_profile(rpdo=[{**hold, "shared": True}, control])},
            r"profile.rpdo.0.objects: a shared RPDO carries each drive's target torque 0x6071 "
            "only",
        ),
        (
            {"profile": compact_profile(rpdo=[{**torque, "shared": True}, hold])},
            r"profile.rpdo: no RPDO maps 0x6040 \+ 0x6071 \+ 0x6060 together, nor are 0x6071 "
            r"and 0x6040 \+ 0x6060 \(without a target\) mapped in two RPDOs",
        ),
        (
            {"profile": compact_profile(tpdo=[{**compact_profile()["tpdo"][0], "shared": True}])},
            r"profile.tpdo.0.shared: only an RPDO: each drive sends its own TPDOs",
        ),
        (
            {"profile": compact_profile(rpdo=[torque, {**hold, "inhibit_time": 10}, control])},
            r"profile.rpdo.1.inhibit_time: only an event-driven TPDO has one",
        ),
        (
            {
                "profile": compact_profile(
                    tpdo=[
                        {"number": 1, "objects": [0x6064, 0x6041, 0x6061], "transmission_type": 255}
                    ]
                )
            },
            r"profile.tpdo: no TPDO on SYNC \(transmission type 1\) maps 0x6064 \(position "
            r"actual\): it is the host's feedback",
        ),
    ]
    for overrides, message in cases:
        config = drives_config(**overrides)
        with pytest.raises(ValueError, match=message):
            Cia402Driver(config, config.scalings([RADIUS] * len(config.nodes)))
