"""Device side of one ODrive axis (CANSimple) for the simulator, behaving like firmware 0.6.

States: IDLE (power stage off: the mechanical brake engages if fitted, otherwise the
drum free-wheels, the dangerous case the host never chooses as a brake) and
CLOSED_LOOP_CONTROL in POSITION_CONTROL (servo to input_pos -> Actuation.POSITION) or
TORQUE_CONTROL (input_torque -> Actuation.TORQUE), both with PASSTHROUGH input.  Other
control/input modes and the calibration states are refused and counted: the simulated
drive is calibrated and has no velocity loop.  Like the firmware, entering closed loop or
switching to position control sets input_pos to the position estimate (no jump), and in
position control input_torque (Set_Input_Torque, or Set_Input_Pos' torque_ff) is the
torque feed-forward added to the position servo.  Asked for CLOSED_LOOP_CONTROL while
in it, the axis restarts it as the firmware does (input_pos to the estimate, input_torque
to 0: a gap in torque), counted in `restarts`.  The axis powers on IDLE.  A holding brake
opens BRAKE_RELEASE_TIME after the axis arms (a spring-applied brake opens some 20 ms
after its coil is energised; the motor current is up by then) and closes as it disarms.

Cyclic frames from `on_tick`: Heartbeat every heartbeat_period, Get_Encoder_Estimates at
feedback_rate_hz (turns and turns/s from `measure`).  RTR frames for Heartbeat,
Get_Encoder_Estimates and Get_Error are answered at once.

Watchdog (watchdog_timeout set: enable_watchdog on): counts from power-on in every state,
as the firmware's does, so it fires before any host talks unless a frame comes in time;
fed by ANY frame with the axis' node id (commands, remote requests, unknown or malformed
frames alike).  Expiry, an injected fault, Estop or any other axis error latches its error
bits and disarms the axis (IDLE): with a holding brake the brake holds, without one the
winch goes free (torque 0) and a suspended platform falls.  Errors latch until
Clear_Errors (no state request clears them); meanwhile motion commands are refused
(counted) and Set_Axis_State(IDLE) and Estop are obeyed.

Malformed frames (shorter than their DBC length, out-of-range enums) are counted in
`counters.rejected` and ignored; so are NaN/inf floats, which a real ODrive would take:
this one refuses them.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable

import can

from drivers.base import Actuation, FrameCounters, Scaling, VirtualDrive
from drivers.config import DrivesConfig
from drivers.odrive.codec import (
    NODE_ID_MAX,
    AxisError,
    AxisState,
    Cmd,
    ControlMode,
    InputMode,
    OdriveFrameError,
    ProcedureResult,
    decode_clear_errors,
    decode_set_axis_state,
    decode_set_controller_mode,
    decode_set_input_pos,
    decode_set_input_torque,
    encode_encoder_estimates,
    encode_error_status,
    encode_heartbeat,
    is_error_request,
)

_SUPPORTED_MODES = frozenset(
    {
        (ControlMode.POSITION_CONTROL, InputMode.PASSTHROUGH),
        (ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
    }
)
_ERROR_MAX = 0xFFFFFFFF
BRAKE_RELEASE_TIME = 0.02  # s from arming to the holding brake open


class OdriveAxis(VirtualDrive):
    """One simulated ODrive axis at `node_id`, configured like the host side.

    `counters` counts frames addressed to this axis (accepted / rejected by reason),
    `refused` the well-formed commands it would not carry out (by reason), `ignored` the
    frames for it that it has nothing to do with (its own messages, unknown commands).
    """

    def __init__(self, node_id: int, scaling: Scaling, config: DrivesConfig) -> None:
        if not 0 <= node_id <= NODE_ID_MAX:
            raise ValueError(f"ODrive node ids run 0..{NODE_ID_MAX}, not {node_id}")
        if scaling.counts_per_rev != 1.0:
            raise ValueError(f"ODrive node {node_id} reports turns: counts_per_rev must be 1")
        super().__init__(node_id, scaling)
        self.has_holding_brake = config.has_holding_brake
        self.watchdog_timeout = config.watchdog_timeout
        self.heartbeat_period = config.heartbeat_period
        self.estimate_period = 1.0 / config.feedback_rate_hz
        self.counters = FrameCounters()
        self.refused: Counter[str] = Counter()
        self.ignored = 0
        self.restarts = 0  # CLOSED_LOOP_CONTROL asked for while in it
        self.axis_state = AxisState.IDLE
        self.axis_error = 0
        self.disarm_reason = 0
        self.procedure_result = ProcedureResult.SUCCESS
        self.fault_text: str | None = None
        self.control_mode = ControlMode.POSITION_CONTROL
        self.input_mode = InputMode.PASSTHROUGH
        self.input_pos = 0.0  # turns
        self.input_torque = 0.0  # N·m
        self._watchdog_deadline: float | None = None  # None: armed at the first tick
        self._brake_opens: float | None = None  # when the brake opens after arming
        self._brake_open = False
        self._next_heartbeat: float | None = None
        self._next_estimate = 0.0
        self._handlers: dict[int, Callable[[can.Message, float], list[can.Message]]] = {
            Cmd.ESTOP: self._on_estop,
            Cmd.GET_ERROR: self._on_get_error,
            Cmd.SET_AXIS_STATE: self._on_set_axis_state,
            Cmd.SET_CONTROLLER_MODE: self._on_set_controller_mode,
            Cmd.SET_INPUT_POS: self._on_set_input_pos,
            Cmd.SET_INPUT_TORQUE: self._on_set_input_torque,
            Cmd.CLEAR_ERRORS: self._on_clear_errors,
        }
        self._apply()

    # -- VirtualDrive ---------------------------------------------------------------------

    def hears(self, can_id: int) -> bool:
        return can_id >> 5 == self.node_id

    def on_frame(self, message: can.Message, now: float) -> list[can.Message]:
        arbitration_id = message.arbitration_id
        if (
            message.is_extended_id
            or message.is_error_frame
            or arbitration_id >> 5 != self.node_id
            or arbitration_id > 0x7FF
        ):
            return []
        cmd = arbitration_id & 0x1F
        self._feed(now)  # any frame for this node id, as the firmware counts it
        if message.is_remote_frame:
            return self._answer(cmd)
        handler = self._handlers.get(cmd)
        if handler is None:
            self.ignored += 1
            return []
        try:
            return handler(message, now)
        except OdriveFrameError as exc:
            self.counters.reject(exc.reason)
            return []

    def on_tick(self, now: float) -> list[can.Message]:
        if self._expired(now):
            self._fault(AxisError.WATCHDOG_TIMER_EXPIRED, "watchdog timer expired")
        if self._brake_opens is not None and now >= self._brake_opens:
            self._brake_opens, self._brake_open = None, True
            self._apply()
        out: list[can.Message] = []
        if self._next_heartbeat is None:  # first tick: both cyclic messages start now
            self._next_heartbeat = self._next_estimate = now
        if now >= self._next_heartbeat:
            out.append(self._heartbeat())
            self._next_heartbeat = _next(self._next_heartbeat, self.heartbeat_period, now)
        if now >= self._next_estimate:
            out.append(self._estimate())
            self._next_estimate = _next(self._next_estimate, self.estimate_period, now)
        return out

    def inject_fault(self, code: int, text: str) -> list[can.Message]:
        """Latch `code` (ODrive error bits) and disarm; the next heartbeat reports it, as
        on the real drive (nothing is sent at once)."""
        if not 0 < code <= _ERROR_MAX:
            raise ValueError(f"an ODrive error code is a non-zero u32, not {code}")
        self._fault(code, text)
        return []

    # -- frames -------------------------------------------------------------------------

    def _answer(self, cmd: int) -> list[can.Message]:
        if cmd == Cmd.HEARTBEAT:
            return [self._heartbeat()]
        if cmd == Cmd.GET_ENCODER_ESTIMATES:
            return [self._estimate()]
        if cmd == Cmd.GET_ERROR:
            return [encode_error_status(self.node_id, self.axis_error, self.disarm_reason)]
        self.ignored += 1
        return []

    def _heartbeat(self) -> can.Message:
        return encode_heartbeat(
            self.node_id, self.axis_error, self.axis_state, self.procedure_result
        )

    def _estimate(self) -> can.Message:
        scaling = self.scaling
        return encode_encoder_estimates(
            self.node_id,
            scaling.position(self.length + self.glitch),
            scaling.velocity(self.rate, self.length),
        )

    def _on_estop(self, message: can.Message, now: float) -> list[can.Message]:
        self.counters.accepted += 1
        self._fault(AxisError.ESTOP_REQUESTED, "estop requested")
        return []

    def _on_get_error(self, message: can.Message, now: float) -> list[can.Message]:
        if is_error_request(message):
            self.counters.accepted += 1
            return self._answer(Cmd.GET_ERROR)
        if len(message.data) == 8:  # an answer (this axis' own): nothing to do
            self.ignored += 1
            return []
        raise OdriveFrameError(message, Cmd.GET_ERROR, "dlc", f"{len(message.data)} data bytes")

    def _on_set_axis_state(self, message: can.Message, now: float) -> list[can.Message]:
        state = decode_set_axis_state(message)
        self.counters.accepted += 1
        if state is AxisState.IDLE:
            self._disarm()
        elif state is not AxisState.CLOSED_LOOP_CONTROL:
            self.procedure_result = ProcedureResult.INVALID_STATE
            self.refused[f"unsupported state {state.name}"] += 1
        elif self._accept_motion("Set_Axis_State"):
            self.procedure_result = ProcedureResult.SUCCESS
            if self.axis_state is AxisState.CLOSED_LOOP_CONTROL:
                self.restarts += 1
            elif self.has_holding_brake:
                self._brake_opens = now + BRAKE_RELEASE_TIME
            self._arm()
        return []

    def _on_set_controller_mode(self, message: can.Message, now: float) -> list[can.Message]:
        control, inputs = decode_set_controller_mode(message)
        self.counters.accepted += 1
        if (control, inputs) not in _SUPPORTED_MODES:
            self.refused[f"unsupported mode {control.name}/{inputs.name}"] += 1
        elif self._accept_motion("Set_Controller_Mode"):
            if control is ControlMode.POSITION_CONTROL and control is not self.control_mode:
                self.input_pos = self.scaling.position(self.length)
            self.control_mode, self.input_mode = control, inputs
            self._apply()
        return []

    def _on_set_input_pos(self, message: can.Message, now: float) -> list[can.Message]:
        pos, _vel_ff, torque_ff = decode_set_input_pos(message)  # vel_ff: no velocity loop
        self.counters.accepted += 1
        if self._accept_motion("Set_Input_Pos"):
            self.input_pos = pos
            self.input_torque = torque_ff
            self._apply()
        return []

    def _on_set_input_torque(self, message: can.Message, now: float) -> list[can.Message]:
        torque = decode_set_input_torque(message)
        self.counters.accepted += 1
        if self._accept_motion("Set_Input_Torque"):
            self.input_torque = torque
            self._apply()
        return []

    def _on_clear_errors(self, message: can.Message, now: float) -> list[can.Message]:
        decode_clear_errors(message)
        self.counters.accepted += 1
        self.axis_error = 0
        self.disarm_reason = 0
        self.fault_text = None
        self.procedure_result = ProcedureResult.SUCCESS
        return []

    # -- state --------------------------------------------------------------------------

    def _accept_motion(self, what: str) -> bool:
        if self.axis_error:
            self.refused[f"{what} while in error"] += 1
            return False
        return True

    def _feed(self, now: float) -> None:
        self._watchdog_deadline = now + self.watchdog_timeout

    def _expired(self, now: float) -> bool:
        if self._watchdog_deadline is None:
            self._watchdog_deadline = now + self.watchdog_timeout
            return False
        return now > self._watchdog_deadline

    def _arm(self) -> None:
        """(Re)enter CLOSED_LOOP_CONTROL; position control starts at the estimate, torque
        control at zero torque."""
        self.axis_state = AxisState.CLOSED_LOOP_CONTROL
        self.input_pos = self.scaling.position(self.length)
        self.input_torque = 0.0
        self._apply()

    def _disarm(self) -> None:
        self.axis_state = AxisState.IDLE
        self._brake_opens, self._brake_open = None, False
        self._apply()

    def _fault(self, code: int, text: str) -> None:
        """Latch error bits and disarm (IDLE), as firmware 0.6 does on every axis error."""
        self.axis_error |= code
        self.disarm_reason = code
        self.fault_text = text
        self._disarm()

    def _apply(self) -> None:
        """The power stage and brake for the current state and mode."""
        if self.axis_state is not AxisState.CLOSED_LOOP_CONTROL:
            self.actuation = Actuation.OFF
            self.force = 0.0
            self.target_length = math.nan
            self.brake_engaged = self.has_holding_brake
            return
        self.brake_engaged = self.has_holding_brake and not self._brake_open
        if self.control_mode is ControlMode.POSITION_CONTROL:
            self.actuation = Actuation.POSITION
            self.target_length = self.scaling.length(self.input_pos)
            self.force = self.scaling.force(self.input_torque, self.length)  # the feed-forward
        else:
            self.actuation = Actuation.TORQUE
            self.force = self.scaling.force(self.input_torque, self.length)
            self.target_length = math.nan


def _next(due: float, period: float, now: float) -> float:
    """The next due time of a cyclic message; after a stall, one period from now."""
    due += period
    return due if due > now else now + period
