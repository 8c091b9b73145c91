"""The simulated ODrive axis, alone and against the host driver over an in-memory link.

`SimLink` runs in simulated time (1 ms ticks): host frames reach every device at once,
device frames reach the driver's `receive` and then a pending `expect`.  Coroutines run
with asyncio.run and never wait on a wall clock.
"""

from __future__ import annotations

import asyncio
import math
import struct
from collections import deque
from collections.abc import Callable, Sequence

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.base import Actuation, BrakeMode, DriverError, DriveState
from drivers.config import DrivesConfig, parse_drives
from drivers.odrive import codec
from drivers.odrive.codec import AxisError, AxisState, Cmd, ControlMode, InputMode
from drivers.odrive.host import Intent, OdriveDriver
from sim_bus.devices.odrive import OdriveAxis

NODES = [3, 5, 7, 11]
RADII = [0.05, 0.04, 0.06, 0.05]
DIRECTIONS = [1, -1, 1, -1]
LENGTHS = [1.2, 2.5, 0.8, 1.7]
HOLDING = [-120.0, -80.0, -120.0, -80.0]  # N: forces holding a platform at enable
TICK = 0.001


def config(**extra: object) -> DrivesConfig:
    return parse_drives(
        {
            "protocol": "odrive",
            "nodes": NODES,
            "gear_ratio": 5.0,
            "direction": DIRECTIONS,
            "length_offset": [1.0, 2.0, 0.5, 1.5],
            **extra,
        }
    )


def axes(cfg: DrivesConfig) -> list[OdriveAxis]:
    devices = [
        OdriveAxis(node, scaling, cfg)
        for node, scaling in zip(cfg.nodes, cfg.scalings(RADII), strict=True)
    ]
    for device, length in zip(devices, LENGTHS, strict=True):
        device.measure(length, 0.0)
    return devices


def closed_loop(device: OdriveAxis, now: float = 0.0) -> OdriveAxis:
    """`device` asked into CLOSED_LOOP_CONTROL (position control at its length)."""
    device.on_frame(codec.encode_set_axis_state(device.node_id, AxisState.CLOSED_LOOP_CONTROL), now)
    assert device.axis_state is AxisState.CLOSED_LOOP_CONTROL
    return device


class SimLink:
    """The bus between one driver and its devices, in simulated time."""

    def __init__(self, driver: OdriveDriver, devices: Sequence[OdriveAxis]) -> None:
        self.driver = driver
        self.devices = list(devices)
        self.ticks = 0
        self.sent: list[can.Message] = []  # by the host
        self.heard: list[can.Message] = []  # from the devices, as the host received them
        self.inbox: deque[can.Message] = deque()

    @property
    def t(self) -> float:
        return self.ticks * TICK

    def now(self) -> float:
        return self.t

    def send(self, message: can.Message) -> None:
        self.sent.append(message)
        for device in self.devices:
            self.inbox.extend(device.on_frame(message, self.t))

    def send_all(self, messages: Sequence[can.Message]) -> None:
        for message in messages:
            self.send(message)

    def _tick(self) -> None:
        self.ticks += 1
        for device in self.devices:
            self.inbox.extend(device.on_tick(self.t))

    def _next(self) -> can.Message | None:
        """The oldest device frame that has reached the host (at once, here), taken."""
        return self.inbox.popleft() if self.inbox else None

    def _drain(self, match: Callable[[can.Message], bool] | None = None) -> can.Message | None:
        while (message := self._next()) is not None:
            self.heard.append(message)
            self.driver.receive(message, self.t)
            if match is not None and match(message):
                return message
        return None

    async def expect(
        self, match: Callable[[can.Message], bool], timeout: float, what: str
    ) -> can.Message:
        end = self.ticks + max(1, round(timeout / TICK))
        while True:
            found = self._drain(match)
            if found is not None:
                return found
            if self.ticks >= end:
                raise DriverError(f"timeout waiting for {what}")
            self._tick()

    def run(self, seconds: float, each_tick: Callable[[], None] | None = None) -> None:
        """Let time pass; `each_tick` runs once per ms (e.g. the host's cycle)."""
        for _ in range(round(seconds / TICK)):
            self._tick()
            self._drain()
            if each_tick is not None:
                each_tick()


def setup(**extra: object) -> tuple[OdriveDriver, list[OdriveAxis], SimLink]:
    cfg = config(**extra)
    driver = OdriveDriver(cfg, cfg.scalings(RADII))
    devices = axes(cfg)
    return driver, devices, SimLink(driver, devices)


def started(**extra: object) -> tuple[OdriveDriver, list[OdriveAxis], SimLink]:
    driver, devices, link = setup(**extra)
    asyncio.run(driver.start(link, link.now))
    return driver, devices, link


def enabled(**extra: object) -> tuple[OdriveDriver, list[OdriveAxis], SimLink]:
    driver, devices, link = started(**extra)
    link.run(0.005)  # fresh estimates (a start with brakes does not wait for them)
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    return driver, devices, link


def frame(node: int, cmd: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=node << 5 | cmd, data=data, is_extended_id=False)


# -- the device alone -----------------------------------------------------------------------


def test_power_on_is_idle_braked_or_free() -> None:
    braked = axes(config(has_holding_brake=True))[0]
    assert braked.axis_state is AxisState.IDLE
    assert braked.actuation is Actuation.OFF and braked.brake_engaged
    # An IDLE axis without a brake free-wheels: what the host must never choose.
    free = axes(config())[0]
    assert free.axis_state is AxisState.IDLE
    assert free.actuation is Actuation.OFF and not free.brake_engaged


@pytest.mark.parametrize("has_brake", [False, True])
def test_watchdog_fires_at_power_on_before_any_host_talks(has_brake: bool) -> None:
    """Firmware 0.6 counts the axis watchdog from power-on, in IDLE too."""
    device = axes(config(has_holding_brake=has_brake, watchdog_timeout=0.05))[0]
    for k in range(1, 50):
        device.on_tick(k * TICK)
    assert device.axis_error == 0
    for k in range(50, 60):
        device.on_tick(k * TICK)
    assert device.axis_error == AxisError.WATCHDOG_TIMER_EXPIRED
    assert device.axis_state is AxisState.IDLE and device.brake_engaged is has_brake
    (heartbeat,) = device.on_frame(codec.encode_request(3, Cmd.HEARTBEAT), 0.06)
    assert codec.decode_heartbeat(heartbeat)[:2] == (AxisError.WATCHDOG_TIMER_EXPIRED, 1)


def test_cyclic_heartbeat_and_estimates() -> None:
    device = axes(config(feedback_rate_hz=250.0, heartbeat_period=0.1, watchdog_timeout=10.0))[1]
    device.measure(LENGTHS[1], 0.3)
    out: list[can.Message] = []
    for k in range(1, 1001):
        out.extend(device.on_tick(k * TICK))
    heartbeats = [m for m in out if m.arbitration_id == 5 << 5 | Cmd.HEARTBEAT]
    estimates = [m for m in out if m.arbitration_id == 5 << 5 | Cmd.GET_ENCODER_ESTIMATES]
    assert len(heartbeats) == 10 and len(estimates) == 250
    pos, vel = codec.decode_encoder_estimates(estimates[-1])
    assert pos == pytest.approx(device.scaling.position(LENGTHS[1]), rel=1e-6)
    assert vel == pytest.approx(device.scaling.velocity(0.3), rel=1e-6)
    assert codec.decode_heartbeat(heartbeats[0]).axis_state is AxisState.IDLE
    assert all(len(m.data) == 8 for m in heartbeats + estimates)


def test_remote_requests_are_answered_at_once() -> None:
    device = axes(config())[0]
    for cmd in (Cmd.HEARTBEAT, Cmd.GET_ENCODER_ESTIMATES, Cmd.GET_ERROR):
        (answer,) = device.on_frame(codec.encode_request(3, cmd), 0.0)
        assert answer.arbitration_id == 3 << 5 | cmd and not answer.is_remote_frame
    assert device.on_frame(codec.encode_request(3, Cmd.SET_INPUT_TORQUE), 0.0) == []
    assert device.on_frame(codec.encode_request(4, Cmd.HEARTBEAT), 0.0) == []
    (answer,) = device.on_frame(frame(3, Cmd.GET_ERROR, b"\x00"), 0.0)  # with an error type
    assert codec.decode_error_status(answer) == (0, 0)


def test_torque_and_position_commands_drive_the_winch() -> None:
    device = closed_loop(axes(config())[1])  # direction -1
    device.on_frame(codec.encode_set_input_torque(5, 0.4), 0.0)
    assert device.actuation is Actuation.POSITION  # position control: torque only stored
    device.on_frame(
        codec.encode_set_controller_mode(5, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
        0.0,
    )
    assert device.actuation is Actuation.TORQUE
    assert device.force == pytest.approx(-0.4 * 5.0 / 0.04, rel=1e-6)  # direction -1
    device.on_frame(codec.encode_set_input_torque(5, -0.2), 0.001)
    assert device.force == pytest.approx(0.2 * 5.0 / 0.04, rel=1e-6)
    device.on_frame(
        codec.encode_set_controller_mode(5, ControlMode.POSITION_CONTROL, InputMode.PASSTHROUGH),
        0.002,
    )
    assert device.actuation is Actuation.POSITION
    assert device.target_length == pytest.approx(LENGTHS[1])  # holds where it is
    turns = device.scaling.position(2.6)
    device.on_frame(codec.encode_set_input_pos(5, turns), 0.003)
    assert device.target_length == pytest.approx(2.6, rel=1e-6)
    device.on_frame(codec.encode_set_axis_state(5, AxisState.IDLE), 0.004)
    assert device.actuation is Actuation.OFF and not device.brake_engaged
    assert device.counters.accepted == 7 and device.counters.rejected_total == 0


def test_unsupported_states_and_modes_are_refused() -> None:
    device = closed_loop(axes(config())[0])
    device.on_frame(codec.encode_set_axis_state(3, AxisState.FULL_CALIBRATION_SEQUENCE), 0.0)
    assert device.axis_state is AxisState.CLOSED_LOOP_CONTROL
    assert device.procedure_result == codec.ProcedureResult.INVALID_STATE
    heartbeat = codec.decode_heartbeat(
        device.on_frame(codec.encode_request(3, Cmd.HEARTBEAT), 0)[0]
    )
    assert heartbeat.procedure_result == codec.ProcedureResult.INVALID_STATE
    device.on_frame(
        codec.encode_set_controller_mode(3, ControlMode.VELOCITY_CONTROL, InputMode.VEL_RAMP), 0.0
    )
    assert device.control_mode is ControlMode.POSITION_CONTROL
    assert device.refused == {
        "unsupported state FULL_CALIBRATION_SEQUENCE": 1,
        "unsupported mode VELOCITY_CONTROL/VEL_RAMP": 1,
    }


def test_device_refuses_non_finite_and_malformed_frames() -> None:
    device = closed_loop(axes(config())[0])
    device.on_frame(
        codec.encode_set_controller_mode(3, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH), 0
    )
    device.on_frame(codec.encode_set_input_torque(3, 0.5), 0.0)
    force = device.force
    hostile = [
        frame(3, Cmd.SET_INPUT_TORQUE, struct.pack("<f4x", math.nan)),
        frame(3, Cmd.SET_INPUT_TORQUE, struct.pack("<f4x", -math.inf)),
        frame(3, Cmd.SET_INPUT_TORQUE, bytes(2)),
        frame(3, Cmd.SET_INPUT_TORQUE, struct.pack("<f", 0.1)),  # 4 bytes: the DBC says 8
        frame(3, Cmd.SET_INPUT_POS, struct.pack("<fhh", math.nan, 0, 0)),
        frame(3, Cmd.SET_AXIS_STATE, struct.pack("<I4x", 99)),
        frame(3, Cmd.SET_AXIS_STATE, struct.pack("<I", 1)),  # IDLE in 4 bytes: refused
        frame(3, Cmd.CLEAR_ERRORS, b""),
        frame(3, Cmd.SET_CONTROLLER_MODE, struct.pack("<II", 7, 1)),
        frame(3, Cmd.SET_CONTROLLER_MODE, bytes(4)),
        frame(3, Cmd.GET_ERROR, bytes(3)),
    ]
    for message in hostile:
        assert device.on_frame(message, 0.01) == []
    assert device.counters.rejected == {
        "Set_Input_Torque.non_finite": 2,
        "Set_Input_Torque.dlc": 2,
        "Set_Input_Pos.non_finite": 1,
        "Set_Axis_State.axis_state": 1,
        "Set_Axis_State.dlc": 1,
        "Clear_Errors.dlc": 1,
        "Set_Controller_Mode.control_mode": 1,
        "Set_Controller_Mode.dlc": 1,
        "Get_Error.dlc": 1,
    }
    assert device.force == force and device.actuation is Actuation.TORQUE
    # Frames for other nodes, extended ids and its own messages change nothing either.
    for message in [
        codec.encode_set_input_torque(4, 9.0),
        can.Message(arbitration_id=3 << 5 | 0x0E, data=bytes(4), is_extended_id=True),
        codec.encode_heartbeat(3, 0, AxisState.IDLE),
        frame(3, 0x1F, bytes(8)),
    ]:
        assert device.on_frame(message, 0.02) == []
    assert device.force == force and device.ignored == 2


@given(st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), max_size=40))
def test_device_never_raises_and_ignores_other_nodes(frames) -> None:
    device = axes(config())[0]
    before = (device.actuation, device.target_length, device.axis_state, device.axis_error)
    for arbitration_id, data in frames:
        if arbitration_id >> 5 == 3:
            arbitration_id ^= 1 << 5  # another node
        message = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        assert device.on_frame(message, 0.0) == []
    assert (device.actuation, device.target_length, device.axis_state, device.axis_error) == before


@given(st.lists(st.tuples(st.integers(0, 0x1F), st.binary(max_size=8)), max_size=40))
def test_device_survives_anything_addressed_to_it(frames) -> None:
    device = axes(config())[0]
    for cmd, data in frames:
        for answer in device.on_frame(frame(3, cmd, data), 0.0):
            assert answer.arbitration_id >> 5 == 3
    assert math.isfinite(device.force)
    assert device.actuation is not Actuation.POSITION or math.isfinite(device.target_length)
    assert device.actuation is not Actuation.OFF or device.brake_engaged is False


def test_flood_leaves_the_drive_in_control() -> None:
    device = closed_loop(axes(config())[0])
    junk = frame(3, Cmd.SET_INPUT_POS, struct.pack("<fhh", math.inf, 0, 0))
    for k in range(20000):
        device.on_frame(junk, k * 1e-5)
    assert device.counters.rejected["Set_Input_Pos.non_finite"] == 20000
    assert device.target_length == pytest.approx(LENGTHS[0])


@pytest.mark.parametrize(
    "extra",
    [{}, {"has_holding_brake": True}, {"has_holding_brake": True, "brake": "holding_brake"}],
)
def test_any_axis_error_disarms_the_axis_as_firmware_0_6_does(extra) -> None:
    """Whatever DrivesConfig.brake says: IDLE, the brake holds where fitted, otherwise the
    winch goes free (torque 0) and a suspended platform falls."""
    has_brake = bool(extra.get("has_holding_brake"))
    device = closed_loop(axes(config(**extra))[0])
    device.on_frame(
        codec.encode_set_controller_mode(3, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH), 0
    )
    device.on_frame(codec.encode_set_input_torque(3, -0.3), 0.0)
    assert device.actuation is Actuation.TORQUE and device.force != 0.0
    assert device.inject_fault(AxisError.DRV_FAULT, "gate driver fault") == []
    assert device.axis_error == AxisError.DRV_FAULT and device.fault_text == "gate driver fault"
    assert (device.actuation, device.axis_state) == (Actuation.OFF, AxisState.IDLE)
    assert device.force == 0.0 and device.brake_engaged is has_brake
    (heartbeat,) = device.on_frame(codec.encode_request(3, Cmd.HEARTBEAT), 0.0)
    assert codec.decode_heartbeat(heartbeat)[:2] == (AxisError.DRV_FAULT, AxisState.IDLE)
    with pytest.raises(ValueError, match="non-zero u32"):
        device.inject_fault(0, "nothing")


def test_fault_on_an_idle_axis_keeps_it_idle() -> None:
    device = axes(config(has_holding_brake=True))[0]
    device.inject_fault(AxisError.MOTOR_OVER_TEMP, "hot")
    assert device.axis_state is AxisState.IDLE and device.brake_engaged
    assert device.actuation is Actuation.OFF


def test_errors_latch_until_clear_errors() -> None:
    device = closed_loop(axes(config())[0])
    device.inject_fault(AxisError.SPINOUT_DETECTED, "spinout")
    for message in [
        codec.encode_set_controller_mode(3, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
        codec.encode_set_input_pos(3, 100.0),
        codec.encode_set_input_torque(3, 1.0),
        codec.encode_set_axis_state(3, AxisState.CLOSED_LOOP_CONTROL),
    ]:
        device.on_frame(message, 0.0)
    assert device.actuation is Actuation.OFF and device.axis_state is AxisState.IDLE
    assert sum(device.refused.values()) == 4  # no state request clears the error
    (status,) = device.on_frame(codec.encode_request(3, Cmd.GET_ERROR), 0.0)
    assert codec.decode_error_status(status) == (AxisError.SPINOUT_DETECTED,) * 2
    device.on_frame(codec.encode_clear_errors(3), 0.0)
    assert device.axis_error == 0 and device.fault_text is None
    assert device.axis_state is AxisState.IDLE  # clearing changes no state
    closed_loop(device)
    device.on_frame(codec.encode_set_input_pos(3, 100.0), 0.0)
    assert device.target_length == pytest.approx(device.scaling.length(100.0))


def test_estop_idles_the_axis_and_without_a_brake_it_free_wheels() -> None:
    for has_brake in (False, True):
        device = closed_loop(axes(config(has_holding_brake=has_brake))[0])
        device.on_frame(codec.encode_estop(3), 0.0)
        assert device.axis_error == AxisError.ESTOP_REQUESTED
        assert device.axis_state is AxisState.IDLE and device.actuation is Actuation.OFF
        assert device.brake_engaged is has_brake


def test_watchdog_expiry_on_the_device() -> None:
    device = closed_loop(axes(config(watchdog_timeout=0.05))[0])
    device.on_frame(
        codec.encode_set_controller_mode(3, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH), 0
    )
    for k in range(1, 101):  # fed every 10 ms for 1 s: no expiry
        now = k * 0.01
        device.on_frame(codec.encode_set_input_torque(3, 0.1), now)
        device.on_tick(now)
    assert device.axis_error == 0 and device.actuation is Actuation.TORQUE
    # Any frame with its node id feeds it, as the firmware counts: requests, malformed
    # frames, unknown commands.
    feeds = [
        codec.encode_request(3, Cmd.HEARTBEAT),
        frame(3, Cmd.SET_INPUT_TORQUE, bytes(2)),
        frame(3, 0x1F, bytes(8)),
    ]
    for k in range(1, 301):
        now = 1.0 + k * TICK
        if k % 40 == 0:
            device.on_frame(feeds[k // 40 % 3], now)
        device.on_tick(now)
    assert device.axis_error == 0 and device.actuation is Actuation.TORQUE
    for k in range(1, 60):  # frames for another node do not
        now = 1.3 + k * TICK
        device.on_frame(codec.encode_set_input_torque(4, 0.1), now)
        device.on_tick(now)
    assert device.axis_error == AxisError.WATCHDOG_TIMER_EXPIRED
    assert device.actuation is Actuation.OFF and not device.brake_engaged  # no brake: free


def test_closed_loop_asked_again_restarts_the_axis() -> None:
    """What firmware does and the host must avoid: input reset, a gap in torque."""
    device = closed_loop(axes(config())[0])
    device.on_frame(
        codec.encode_set_controller_mode(3, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH), 0
    )
    device.on_frame(codec.encode_set_input_torque(3, -0.3), 0.0)
    closed_loop(device)
    assert device.restarts == 1 and device.force == 0.0


# -- host <-> device -------------------------------------------------------------------------


def test_start_without_brakes_holds_the_measured_lengths() -> None:
    driver, devices, link = setup()
    link.run(0.2)  # powered up, no host yet: every watchdog expires (free winches)
    assert all(d.axis_error == AxisError.WATCHDOG_TIMER_EXPIRED for d in devices)
    assert all(d.actuation is Actuation.OFF for d in devices)
    assert all(s.state is DriveState.FAULT for s in driver.status)
    asyncio.run(driver.start(link, link.now))
    for i, device in enumerate(devices):
        assert device.axis_state is AxisState.CLOSED_LOOP_CONTROL and device.axis_error == 0
        assert device.actuation is Actuation.POSITION
        assert device.target_length == pytest.approx(LENGTHS[i], abs=1e-6)
        assert driver.status[i].state is DriveState.HOLDING
        assert driver.feedback[i].length == pytest.approx(LENGTHS[i], abs=1e-6)
        assert driver.intent[i] is Intent.HOLD_POSITION
    sent = [m.arbitration_id & 0x1F for m in link.sent]
    assert Cmd.CLEAR_ERRORS in sent and Cmd.ESTOP not in sent
    assert AxisState.IDLE not in [
        codec.decode_set_axis_state(m) for m in link.sent if m.arbitration_id & 0x1F == 7
    ]
    # The daemon then feeds the holds every cycle: they stay without error.
    link.run(1.0, lambda: link.send_all(driver.keepalive()))
    assert all(d.axis_error == 0 for d in devices)
    assert all(s.state is DriveState.HOLDING for s in driver.status)


def test_start_with_brakes_leaves_the_axes_idle_and_braked() -> None:
    driver, devices, link = started(has_holding_brake=True)
    for i, device in enumerate(devices):
        assert device.axis_state is AxisState.IDLE and device.brake_engaged
        assert driver.status[i].state is DriveState.READY
    link.run(1.0, lambda: link.send_all(driver.keepalive()))  # IDLE: fed by requests
    assert all(d.axis_error == 0 for d in devices)
    link.run(0.2)  # a dead host: the watchdog counts in IDLE too
    assert all(d.axis_error == AxisError.WATCHDOG_TIMER_EXPIRED for d in devices)
    assert all(d.brake_engaged for d in devices)


def test_start_names_the_silent_nodes() -> None:
    driver, devices, link = setup()
    link.devices = devices[:2]  # nodes 7 and 11 never answer
    with pytest.raises(DriverError, match="no heartbeat") as info:
        asyncio.run(driver.start(link, link.now))
    message = str(info.value)
    assert "node 7" in message and "node 11" in message
    assert "node 3" not in message and "node 5" not in message


def test_enable_then_commands_reach_the_winches_as_forces() -> None:
    driver, devices, link = enabled()
    for i, device in enumerate(devices):
        assert device.actuation is Actuation.TORQUE
        assert device.force == pytest.approx(HOLDING[i], rel=1e-6)  # never a dropped load
        assert driver.status[i].state is DriveState.ENABLED
    forces = [-120.0, -80.0, -40.5, -10.0]
    link.send_all(driver.commands(forces))
    for device, force in zip(devices, forces, strict=True):
        assert device.force == pytest.approx(force, rel=1e-6)
    # Commanding every 2 ms keeps every watchdog fed.
    link.run(1.0, lambda: link.send_all(driver.commands(forces)) if link.ticks % 2 else None)
    assert all(d.axis_error == 0 and d.actuation is Actuation.TORQUE for d in devices)


def test_enable_holds_position_on_the_way() -> None:
    driver, _, link = started()
    lengths = [1.0, 2.0, 3.0, 4.0]
    asyncio.run(driver.enable(link, lengths, HOLDING))
    modes = [
        codec.decode_set_controller_mode(m)[0]
        for m in link.sent
        if m.arbitration_id == NODES[0] << 5 | Cmd.SET_CONTROLLER_MODE
    ]
    assert modes[-2:] == [ControlMode.POSITION_CONTROL, ControlMode.TORQUE_CONTROL]
    last_torque = [m for m in link.sent if m.arbitration_id == NODES[0] << 5 | 0x0E][-1]
    # the drive takes up the holding force with the mode change, never zero torque
    assert driver.scalings[0].force(codec.decode_set_input_torque(last_torque)) == pytest.approx(
        HOLDING[0], rel=1e-6
    )
    with pytest.raises(ValueError, match="finite lengths"):
        asyncio.run(driver.enable(link, [math.nan] * 4, HOLDING))


def test_enable_fails_on_a_faulted_drive_and_names_it() -> None:
    driver, devices, link = started()
    devices[2].inject_fault(AxisError.INVERTER_OVER_TEMP, "hot")
    with pytest.raises(DriverError, match="enable") as info:
        asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    assert "node 7" in str(info.value) and "INVERTER_OVER_TEMP" in str(info.value)
    assert "node 3" not in str(info.value)
    assert devices[2].actuation is Actuation.OFF  # firmware 0.6: disarmed by the error


class LaggingLink(SimLink):
    """Device frames reach the host `lag` seconds after they were sent (a loaded host or
    a slow guest reading its socket late); host frames reach the devices at once."""

    def __init__(self, driver: OdriveDriver, devices: Sequence[OdriveAxis], lag: float) -> None:
        super().__init__(driver, devices)
        self.lag = lag
        self.sent_at: deque[float] = deque()  # when each inbox frame was sent

    def _next(self) -> can.Message | None:
        while len(self.sent_at) < len(self.inbox):
            self.sent_at.append(self.t)
        if not self.inbox or self.sent_at[0] + self.lag > self.t + 1e-9:
            return None
        self.sent_at.popleft()
        return self.inbox.popleft()


@pytest.mark.parametrize("lag_ms", range(0, 100, 5))  # below the heartbeat period
def test_a_heartbeat_sent_before_enable_reached_the_drive_does_not_undo_it(lag_ms: int) -> None:
    """A braked drive's heartbeat sent before it took Set_Axis_State(CLOSED_LOOP_CONTROL)
    and read after the request went out still shows IDLE: taken as a refusal, the host
    would put the axis back on its brake (a braked idle axis is kept braked) and enable
    would time out with every axis IDLE.  A heartbeat is taken as a refusal only where it
    arrived a heartbeat period (0.1 s) after the request: with any lag below that,
    enable reaches closed loop."""
    cfg = config(has_holding_brake=True)
    driver = OdriveDriver(cfg, cfg.scalings(RADII))
    devices = axes(cfg)
    link = LaggingLink(driver, devices, lag_ms / 1000)
    asyncio.run(driver.start(link, link.now))
    # the host's cycle feeds the watchdogs; the next periodic heartbeats go out just
    # before the requests
    link.run(0.095, lambda: link.send_all(driver.keepalive()))
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    assert all(d.axis_state is AxisState.CLOSED_LOOP_CONTROL for d in devices)
    assert driver.intent == [Intent.TORQUE] * 4


def test_sequences_need_start_first() -> None:
    driver, _, link = setup()
    with pytest.raises(DriverError, match="start"):
        asyncio.run(driver.enable(link, LENGTHS, HOLDING))
    with pytest.raises(DriverError, match="start"):
        asyncio.run(driver.reset_faults(link))


@pytest.mark.parametrize(
    ("extra", "brake"),
    [({}, False), ({"has_holding_brake": True, "brake": "holding_brake"}, True)],
)
def test_dead_host_ends_disarmed_by_the_watchdog(extra, brake) -> None:
    """Firmware 0.6: IDLE, so only a holding brake keeps the load; without one the
    winch is free (what check-config refuses unless accepted)."""
    driver, devices, link = enabled(**extra)
    link.send_all(driver.commands([-50.0] * 4))
    link.run(0.2)  # the daemon stops: no commands, no keepalive
    for i, device in enumerate(devices):
        assert device.axis_error & AxisError.WATCHDOG_TIMER_EXPIRED
        assert device.actuation is Actuation.OFF and device.brake_engaged is brake
        status = driver.status[i]
        assert status.state is DriveState.FAULT
        assert "WATCHDOG_TIMER_EXPIRED" in status.fault
        assert status.fault_code == AxisError.WATCHDOG_TIMER_EXPIRED


@pytest.mark.parametrize(
    ("extra", "end_state"),
    [({}, DriveState.HOLDING), ({"has_holding_brake": True}, DriveState.READY)],
)
def test_reset_faults_clears_and_holds(extra, end_state) -> None:
    driver, devices, link = enabled(**extra)
    link.run(0.2)
    assert all(s.state is DriveState.FAULT for s in driver.status)
    asyncio.run(driver.reset_faults(link))
    for i, device in enumerate(devices):
        assert device.axis_error == 0
        assert driver.status[i].state is end_state and driver.status[i].fault is None
        assert device.actuation is not Actuation.TORQUE
        assert device.brake_engaged or device.actuation is Actuation.POSITION  # never loose


def test_reset_after_estop_rearms_the_hold() -> None:
    driver, devices, link = started()
    link.send(codec.encode_estop(NODES[1]))  # someone else's estop: the drum free-wheels
    assert devices[1].actuation is Actuation.OFF and not devices[1].brake_engaged
    link.run(0.15, lambda: link.send_all(driver.keepalive()))
    assert driver.status[1].state is DriveState.FAULT
    assert "ESTOP_REQUESTED" in driver.status[1].fault
    asyncio.run(driver.reset_faults(link))
    assert devices[1].axis_state is AxisState.CLOSED_LOOP_CONTROL
    assert devices[1].actuation is Actuation.POSITION
    assert driver.status[1].state is DriveState.HOLDING


def test_brake_modes_on_the_devices() -> None:
    driver, devices, link = enabled(has_holding_brake=True)
    assert all(d.brake_engaged for d in devices)  # armed: the brakes open 20 ms later
    link.run(0.03, lambda: link.send_all(driver.commands(HOLDING)))
    assert not any(d.brake_engaged for d in devices)
    link.send_all(driver.brake([f.length for f in driver.feedback], BrakeMode.POSITION_HOLD))
    assert all(d.actuation is Actuation.POSITION and not d.brake_engaged for d in devices)
    link.run(0.5, lambda: link.send_all(driver.keepalive()))
    assert all(d.axis_error == 0 for d in devices)
    assert all(s.state is DriveState.HOLDING for s in driver.status)
    link.send_all(driver.brake([f.length for f in driver.feedback], BrakeMode.HOLDING_BRAKE))
    assert all(d.actuation is Actuation.OFF and d.brake_engaged for d in devices)
    link.run(0.5, lambda: link.send_all(driver.keepalive()))
    assert all(d.axis_error == 0 for d in devices)
    assert all(s.state is DriveState.HOLDING for s in driver.status)


def test_force_commands_after_a_brake_do_not_release_it() -> None:
    driver, devices, link = enabled()
    link.send_all(driver.brake([f.length for f in driver.feedback], BrakeMode.POSITION_HOLD))
    link.send_all(driver.commands([500.0] * 4))
    assert all(d.actuation is Actuation.POSITION for d in devices)
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    assert [d.force for d in devices] == pytest.approx(HOLDING, rel=1e-6)
    link.send_all(driver.commands([-5.0] * 4))
    assert all(d.force == pytest.approx(-5.0, rel=1e-6) for d in devices)


@pytest.mark.parametrize("extra", [{}, {"has_holding_brake": True}])
def test_braking_and_enabling_never_restart_an_axis(extra) -> None:
    """Set_Axis_State(CLOSED_LOOP_CONTROL) reaches an axis only when it is not in closed
    loop: braking a torque-controlled axis, enabling a holding one and resetting a
    healthy one leave the firmware's closed loop running (no torque gap)."""
    driver, devices, link = enabled(**extra)
    link.run(0.2, lambda: link.send_all(driver.commands([-50.0] * 4)))
    link.send_all(driver.brake([f.length for f in driver.feedback], BrakeMode.POSITION_HOLD))
    assert all(d.actuation is Actuation.POSITION for d in devices)
    link.run(0.2, lambda: link.send_all(driver.keepalive()))
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    asyncio.run(driver.reset_faults(link))  # with a brake: IDLE, asked once
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    link.run(0.2, lambda: link.send_all(driver.commands(HOLDING)))
    assert all(d.actuation is Actuation.TORQUE and d.axis_error == 0 for d in devices)
    assert [d.restarts for d in devices] == [0] * 4
    states = [codec.decode_set_axis_state(m) for m in link.sent if m.arbitration_id & 0x1F == 7]
    assert states.count(AxisState.CLOSED_LOOP_CONTROL) == 4 * (2 if extra else 1)  # from IDLE


def test_disable_idles_the_devices() -> None:
    driver, devices, link = enabled(has_holding_brake=True)
    link.send_all(driver.disable())
    link.run(0.15, lambda: link.send_all(driver.keepalive()))  # the idle watchdogs fed
    assert all(d.actuation is Actuation.OFF and d.brake_engaged for d in devices)
    assert all(s.state is DriveState.READY for s in driver.status)


def test_get_error_round_trip() -> None:
    driver, devices, link = started()
    devices[3].inject_fault(AxisError.BAD_CONFIG, "bad config")
    link.send_all(driver.request_errors())
    link.run(0.001)
    assert driver.drive_errors[3] == (AxisError.BAD_CONFIG, AxisError.BAD_CONFIG)
    assert driver.drive_errors[0] == (0, 0)


def test_host_counts_rejects_from_a_babbling_drive() -> None:
    driver, _, link = started()
    count = driver.feedback[0].count
    link.inbox.extend(
        [frame(NODES[0], 9, struct.pack("<ff", math.nan, 0.0))] * 100
        + [frame(NODES[0], 1, bytes(2))] * 10
    )
    link.run(0.0)
    link._drain()
    assert driver.counters.rejected["Get_Encoder_Estimates.non_finite"] == 100
    assert driver.counters.rejected["Heartbeat.dlc"] == 10
    assert driver.feedback[0].count == count
