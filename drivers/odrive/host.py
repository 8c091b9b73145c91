"""Host side of ODrive CANSimple (firmware 0.6) for the actuators on one bus.

Timing.CYCLIC: every drive streams Get_Encoder_Estimates at DrivesConfig.feedback_rate_hz
and its Heartbeat every heartbeat_period (drive-side settings: the axis' CAN
encoder_msg_rate_ms and heartbeat_msg_rate_ms); `receive` returns the actuator index on
every accepted estimate.  A force is sent as Set_Input_Torque in N·m at the motor shaft,
lengths arrive as motor turns; both convert through `Scaling` (counts_per_rev = 1: turns).

Axis state requests.  Set_Axis_State goes out only when the axis must change state: not
when its last heartbeat already shows the state, nor when the host asked for it and no
heartbeat has shown it refused since (one that arrived within a heartbeat period of the
request may have left the drive before it).  Firmware restarts an axis that is asked for
CLOSED_LOOP_CONTROL again (input reset, a gap in torque): braking, enable and reset
never do that to an axis in closed loop.

Braking (DESIGN §9).  ODrive's Estop, and IDLE on an axis without a mechanical brake,
cut the motor and let a suspended platform fall: neither is ever used as a brake here.
- POSITION_HOLD: Set_Controller_Mode(POSITION_CONTROL, PASSTHROUGH), Set_Axis_State(
  CLOSED_LOOP_CONTROL) where the axis is not in closed loop, Set_Input_Pos(length,
  torque_ff = the last commanded torque): the drive servoes the cable at `length` and
  keeps carrying the load it carried (firmware resets input_pos to the position estimate
  on the mode change, so the first frame already holds; input_torque is the position
  loop's feed-forward, which a torque_ff of 0 would drop).  Takes effect with no answer;
  `keepalive` re-sends Set_Input_Pos.
- HOLDING_BRAKE: Set_Axis_State(IDLE), only with has_holding_brake: the firmware engages
  the brake when it disarms.  Asked for without a brake, `brake` holds position instead.
  An axis that is IDLE with its brake engaged stays so whichever mode is asked for: its
  brake already holds, and releasing it into a position loop would let the load sag.

Sequences (coroutines on a `Link`):
- start: a heartbeat from every node (DriverError naming the missing ones), then every
  drive is left with its cables held, not idle: with a holding brake, IDLE (brake on,
  READY); without one, closed-loop position control at the length of its first encoder
  estimate (HOLDING), because IDLE would let the platform fall.  Errors are cleared in
  the same batch and the sequence waits for heartbeats showing no error and that state.
- enable: position hold at `lengths` with the enable forces as torque feed-forward (an
  axis leaving its holding brake takes up the load at once), CLOSED_LOOP_CONTROL
  confirmed by heartbeat, then Set_Input_Torque(forces) and Set_Controller_Mode(
  TORQUE_CONTROL, PASSTHROUGH).  After `brake`, a force command only changes the position
  loop's feed-forward (firmware's input_torque): the position loop still holds the
  length until `enable` runs again, so a brake is never released by a stray command.
- reset_faults: Clear_Errors and the same hold as start, confirmed by heartbeats with
  axis_error == 0.
While a sequence waits it feeds the watchdog of every drive not in torque control
(`keepalive` every third of watchdog_timeout) and asks for the awaited frame by RTR, so
it need not wait a whole heartbeat period.

Watchdog: set each axis' enable_watchdog and watchdog_timeout = DrivesConfig.
watchdog_timeout.  Firmware 0.6 counts it down in every axis state, from power-on, and
feeds it on ANY frame with the axis' node id (commands, requests, malformed frames alike).
So `keepalive` feeds every axis that is not following forces: Set_Input_Pos to a drive
holding a position, a Get_Error request (RTR, once per third of watchdog_timeout) to an
idle or braked one.  It never re-sends a force and sends nothing to a drive in torque
control, so a daemon that stops commanding while ENABLED lets the watchdog expire; no
other frame may go to an ODrive node id outside the cycle (it would feed the watchdog).
Firmware disarms the axis (IDLE) on every axis error, watchdog expiry and Estop included:
without a holding brake the platform then falls, which is why `cdprd check-config`
refuses an ODrive robot without drives.has_holding_brake unless the config accepts that
(drives.accept_fall_on_axis_error).  The simulated drive (sim_bus.devices.odrive) does
the same.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence

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
from drivers.config import DrivesConfig
from drivers.odrive.codec import (
    F32,
    FLOAT32_MAX,
    AxisState,
    Cmd,
    ControlMode,
    Heartbeat,
    InputMode,
    OdriveFrameError,
    decode_encoder_estimates,
    decode_error_status,
    decode_heartbeat,
    encode_clear_errors,
    encode_request,
    encode_set_axis_state,
    encode_set_controller_mode,
    error_text,
    input_pos_payload,
    is_error_request,
)

MAX_TORQUE_FF = 32.767  # N·m: Set_Input_Pos' torque_ff is an int16 of 0.001 N·m


class Intent(enum.Enum):
    """What the host last asked a drive to do (the heartbeat does not say)."""

    NONE = "none"
    TORQUE = "torque"  # following force commands
    HOLD_POSITION = "hold_position"  # servoing its cable at a length
    HOLD_BRAKE = "hold_brake"  # IDLE with the mechanical brake engaged


class OdriveDriver(ActuatorDriver):
    """ODrive CANSimple host for config.nodes (cable order), one axis per node.

    `ignored` counts frames that are not this driver's (other nodes, other commands,
    requests); `drive_errors[i]` is the last Get_Error answer (active_errors,
    disarm_reason) of actuator i, asked for with `request_errors`.
    """

    timing = Timing.CYCLIC

    def __init__(
        self,
        config: DrivesConfig,
        scalings: Sequence[Scaling],
        *,
        timeout: float | None = None,
    ) -> None:
        """`scalings` from config.scalings(drum radii); `timeout` bounds each wait of a
        sequence (default: 3 heartbeat timeouts, at least 1 s)."""
        if config.protocol != "odrive":
            raise ValueError(f"OdriveDriver needs protocol odrive, config says {config.protocol}")
        super().__init__(scalings)
        self.nodes = list(config.nodes)
        if len(self.nodes) != self.n:
            raise ValueError(f"{self.n} scalings for {len(self.nodes)} ODrive nodes")
        for node, scaling in zip(self.nodes, self.scalings, strict=True):
            if scaling.counts_per_rev != 1.0:
                raise ValueError(
                    f"ODrive node {node} reports turns: counts_per_rev must be 1, "
                    f"not {scaling.counts_per_rev}"
                )
        self.timeout = max(1.0, 3.0 * config.heartbeat_timeout) if timeout is None else timeout
        if not (math.isfinite(self.timeout) and self.timeout > 0):
            raise ValueError(f"timeout must be positive, not {timeout}")
        self.has_holding_brake = config.has_holding_brake
        self.feed_period = config.watchdog_timeout / 3.0
        self.ignored = 0
        self.drive_errors: list[tuple[int, int] | None] = [None] * self.n
        self.intent = [Intent.NONE] * self.n
        self._axis_state: list[AxisState | int | None] = [None] * self.n
        self._requested: list[AxisState | None] = [None] * self.n  # not yet shown refused
        self._requested_at = [-math.inf] * self.n  # when, by the sequence clock
        self._heartbeat_period = config.heartbeat_period
        self._next_idle_feed = -math.inf
        self._axis_error = [0] * self.n
        self._hold: list[bytes | None] = [None] * self.n  # Set_Input_Pos data while holding
        self._torque = [0.0] * self.n  # N·m the next position hold feeds forward
        self._now: Callable[[], float] | None = None
        self._routes: dict[int, tuple[int, Cmd]] = {
            node << 5 | cmd: (i, cmd)
            for i, node in enumerate(self.nodes)
            for cmd in (Cmd.GET_ENCODER_ESTIMATES, Cmd.HEARTBEAT, Cmd.GET_ERROR)
        }
        self._torque_ids = [node << 5 | Cmd.SET_INPUT_TORQUE for node in self.nodes]
        self._feeds = [encode_request(node, Cmd.GET_ERROR) for node in self.nodes]
        self._pos_ids = [node << 5 | Cmd.SET_INPUT_POS for node in self.nodes]
        # N·m per N, per cable (a drum with a spool: at its latest length, receive)
        self._torque_per_newton = [s.motor_torque(1.0, s.length_offset) for s in self.scalings]
        self._spooled = [s if s.spool is not None else None for s in self.scalings]
        self._metres_per_turn = [s.metres_per_count for s in self.scalings]
        self._offsets = [s.length_offset for s in self.scalings]

    # -- sequences ----------------------------------------------------------------------

    async def start(self, link: Link, now: Callable[[], float]) -> None:
        self._now = now
        await self._collect(link, Cmd.HEARTBEAT, _decodes, "start", "no heartbeat")
        await self._settle(link, "start")

    async def enable(self, link: Link, lengths: Sequence[float], forces: Sequence[float]) -> None:
        self._require_started("enable")
        if len(lengths) != self.n or not all(math.isfinite(x) for x in lengths):
            raise ValueError(f"enable needs {self.n} finite lengths, got {list(lengths)}")
        first = self.commands(forces)  # FrameError on a bad force, before anything moves
        holds = [self._hold_payload(i, length, self._torque[i]) for i, length in enumerate(lengths)]
        for i, hold in enumerate(holds):
            if hold is None:
                raise ValueError(f"actuator {i}: length {lengths[i]} m is no float32 position")
        for i, hold in enumerate(holds):
            self._send_hold(link, i, hold, clear=False)
        await self._confirm(link, AxisState.CLOSED_LOOP_CONTROL, "enable")
        for i, node in enumerate(self.nodes):
            link.send(first[i])  # the input torque, taken up by the mode change
            link.send(
                encode_set_controller_mode(node, ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH)
            )
            self._set_intent(i, Intent.TORQUE, None)

    async def reset_faults(self, link: Link) -> None:
        self._require_started("reset_faults")
        await self._settle(link, "reset_faults")

    def _require_started(self, what: str) -> None:
        if self._now is None:
            raise DriverError(f"ODrive {what}: start() has not run")

    async def _settle(self, link: Link, what: str) -> None:
        """Clear errors and leave every drive holding (brake or position); confirm."""
        if self.has_holding_brake:
            for i, node in enumerate(self.nodes):
                link.send(encode_clear_errors(node))
                for message in self._state_change(i, AxisState.IDLE):
                    link.send(message)
                self._set_intent(i, Intent.NONE, None)
            await self._confirm(link, AxisState.IDLE, what)
            return
        estimates = await self._collect(
            link,
            Cmd.GET_ENCODER_ESTIMATES,
            _decodes,
            what,
            "no encoder estimate",
        )
        for i in range(self.n):
            pos, _ = decode_encoder_estimates(estimates[i])
            self._torque[i] = 0.0  # the load is unknown: the position loop takes it up
            self._send_hold(link, i, input_pos_payload(pos), clear=True)
        await self._confirm(link, AxisState.CLOSED_LOOP_CONTROL, what)

    def _send_hold(self, link: Link, i: int, hold: bytes, *, clear: bool) -> None:
        node = self.nodes[i]
        if clear:
            link.send(encode_clear_errors(node))
        for message in self._hold_frames(i, hold):
            link.send(message)
        self._set_intent(i, Intent.HOLD_POSITION, hold)

    async def _confirm(self, link: Link, state: AxisState, what: str) -> None:
        def reached(i: int, message: can.Message) -> bool:
            heartbeat = decode_heartbeat(message)
            return heartbeat.axis_error == 0 and heartbeat.axis_state is state

        await self._collect(
            link, Cmd.HEARTBEAT, reached, what, f"not in {state.name} without axis error"
        )

    async def _collect(
        self,
        link: Link,
        cmd: Cmd,
        accept: Callable[[int, can.Message], bool],
        what: str,
        failure: str,
    ) -> dict[int, can.Message]:
        """One well-formed frame `cmd` per actuator for which `accept` holds, within
        `timeout`; feeds holding drives and re-asks by RTR every feed period meanwhile.
        DriverError names every node still missing and what was last heard from it."""
        now = self._now
        assert now is not None
        pending = set(range(self.n))
        found: dict[int, can.Message] = {}

        def match(message: can.Message) -> bool:
            route = self._routes.get(message.arbitration_id)
            if (
                route is None
                or route[1] is not cmd
                or route[0] not in pending
                or message.is_extended_id
                or message.is_remote_frame
            ):
                return False
            try:
                return accept(route[0], message)
            except OdriveFrameError:
                return False

        deadline = now() + self.timeout
        next_feed = -math.inf
        while pending:
            t = now()
            if t >= next_feed:
                for message in self.keepalive():
                    link.send(message)
                for i in sorted(pending):
                    link.send(encode_request(self.nodes[i], cmd))
                next_feed = t + self.feed_period
            if t >= deadline:
                raise DriverError(
                    f"ODrive {what}: {failure} within {self.timeout} s from "
                    + "; ".join(self._describe(i) for i in sorted(pending))
                )
            try:
                message = await link.expect(match, min(deadline, next_feed) - t, what)
            except DriverError:
                continue  # a feed period passed without the frame
            index = self._routes[message.arbitration_id][0]
            pending.discard(index)
            found[index] = message
        return found

    def _describe(self, i: int) -> str:
        status = self.status[i]
        node = self.nodes[i]
        state = self._axis_state[i]
        if state is None:
            return f"node {node} (nothing heard)"
        error = self._axis_error[i]
        fault = f", axis error 0x{error:08X} ({error_text(error)})" if error else ""
        return f"node {node} (last heartbeat: {_state_name(state)}{fault}, {status.state.value})"

    # -- immediate frames ----------------------------------------------------------------

    def cycle_start(self) -> list[can.Message]:
        return []

    def commands(self, forces: Sequence[float]) -> list[can.Message]:
        if len(forces) != self.n:
            raise ValueError(f"{len(forces)} forces for {self.n} ODrive actuators")
        pack = F32.pack
        out = []
        for i, force in enumerate(forces):
            torque = force * self._torque_per_newton[i]
            if not -FLOAT32_MAX <= torque <= FLOAT32_MAX:
                raise FrameError(
                    f"actuator {i} (ODrive node {self.nodes[i]}): force {force} N "
                    f"is no finite float32 torque"
                )
            self._torque[i] = torque
            out.append(data_frame(self._torque_ids[i], pack(torque)))
        return out

    def brake(self, lengths: Sequence[float], mode: BrakeMode) -> list[can.Message]:
        """Freeze every cable (see the module docstring).  `lengths` are the host's
        trusted ones; where one is non-finite (none trusted), the mode change alone holds
        at the drive's own position estimate, never at a length some frame reported."""
        if len(lengths) != self.n:
            raise ValueError(f"{len(lengths)} lengths for {self.n} ODrive actuators")
        out: list[can.Message] = []
        by_brake = mode is BrakeMode.HOLDING_BRAKE and self.has_holding_brake
        for i in range(self.n):
            if by_brake or self._braked_idle(i):
                out.extend(self._state_change(i, AxisState.IDLE))
                self._set_intent(i, Intent.HOLD_BRAKE, None)
                continue
            hold = self._hold_payload(i, lengths[i], self._torque[i])
            out.extend(self._hold_frames(i, hold))
            self._set_intent(i, Intent.HOLD_POSITION, hold)
        return out

    def disable(self) -> list[can.Message]:
        """IDLE on every axis: brakes engage where fitted, otherwise the drums free-wheel
        (only for a platform that rests on its support)."""
        out = []
        for i in range(self.n):
            out.extend(self._state_change(i, AxisState.IDLE))
            self._set_intent(i, Intent.NONE, None)
        return out

    def keepalive(self) -> list[can.Message]:
        """Set_Input_Pos again for every drive holding a position (Set_Controller_Mode
        where no length is known); a Get_Error request, once per feed period, to every
        idle or braked drive (its watchdog counts in IDLE too); nothing to a drive
        following forces: never a force."""
        out = []
        now = None if self._now is None else self._now()
        feed_idle = now is None or now >= self._next_idle_feed
        if feed_idle and now is not None:
            self._next_idle_feed = now + self.feed_period
        for i, intent in enumerate(self.intent):
            if intent is Intent.HOLD_POSITION and self._braked_idle(i):
                self._set_intent(i, Intent.HOLD_BRAKE, None)  # its brake holds: keep it so
                intent = Intent.HOLD_BRAKE
            if intent is Intent.HOLD_BRAKE:  # disarmed again if another node armed it
                out.extend(self._state_change(i, AxisState.IDLE))
            if intent is not Intent.HOLD_POSITION:
                if feed_idle and intent is not Intent.TORQUE:
                    out.append(self._feeds[i])
                continue
            # re-armed if another node disarmed it; the control mode, which no frame of
            # firmware 0.6 reports, asked for again every feed period
            out.extend(self._state_change(i, AxisState.CLOSED_LOOP_CONTROL))
            hold = self._hold[i]
            if hold is None or feed_idle:
                out.append(self._position_mode(i))
            if hold is not None:
                out.append(data_frame(self._pos_ids[i], hold))
        return out

    def request_errors(self) -> list[can.Message]:
        """RTR Get_Error to every node; answers land in `drive_errors`."""
        return [encode_request(node, Cmd.GET_ERROR) for node in self.nodes]

    def _hold_payload(self, i: int, length: float, torque: float) -> bytes | None:
        """Set_Input_Pos data holding actuator i at `length` with `torque` (N·m) fed
        forward (none where int16 of 0.001 N·m cannot carry it); None for no length."""
        if not math.isfinite(length):
            return None
        feed_forward = torque if abs(torque) <= MAX_TORQUE_FF else 0.0
        try:
            return input_pos_payload(self.scalings[i].position(length), 0.0, feed_forward)
        except FrameError:
            return None

    def _hold_frames(self, i: int, hold: bytes | None) -> list[can.Message]:
        frames = [self._position_mode(i), *self._state_change(i, AxisState.CLOSED_LOOP_CONTROL)]
        if hold is not None:
            frames.append(data_frame(self._pos_ids[i], hold))
        return frames

    def _braked_idle(self, i: int) -> bool:
        """Axis i is (or was asked to be) IDLE with a holding brake engaged."""
        requested = self._requested[i]
        state = self._axis_state[i] if requested is None else requested
        return self.has_holding_brake and state is AxisState.IDLE

    def _state_change(self, i: int, state: AxisState) -> list[can.Message]:
        """Set_Axis_State(state) unless axis i was asked for `state` and no heartbeat has
        shown it refused since (_on_heartbeat) or, asked for nothing, its last heartbeat
        shows it: never a second CLOSED_LOOP_CONTROL (a restart)."""
        requested = self._requested[i]
        if (self._axis_state[i] if requested is None else requested) is state:
            return []
        self._requested[i] = state
        self._requested_at[i] = -math.inf if self._now is None else self._now()
        return [encode_set_axis_state(self.nodes[i], state)]

    def _position_mode(self, i: int) -> can.Message:
        return encode_set_controller_mode(
            self.nodes[i], ControlMode.POSITION_CONTROL, InputMode.PASSTHROUGH
        )

    def _set_intent(self, i: int, intent: Intent, hold: bytes | None) -> None:
        if intent in (Intent.NONE, Intent.HOLD_BRAKE):
            self._torque[i] = 0.0  # disarmed: nothing to feed forward
        if intent is not self.intent[i]:  # a hold is confirmed by the heartbeats to come
            self.status[i].held, self.status[i].hold_problem = None, None
        self.intent[i] = intent
        self._hold[i] = hold
        self._refresh(i)

    # -- input ----------------------------------------------------------------------------

    def receive_ids(self) -> frozenset[int]:
        return frozenset(self._routes)

    def receive(self, message: can.Message, now: float) -> int | None:
        route = self._routes.get(message.arbitration_id)
        if (
            route is None
            or message.is_extended_id
            or message.is_remote_frame
            or message.is_error_frame
        ):
            self.ignored += 1
            return None
        i, cmd = route
        try:
            if cmd is Cmd.GET_ENCODER_ESTIMATES:
                pos, vel = decode_encoder_estimates(message)
                feedback = self.feedback[i]
                spooled = self._spooled[i]
                if spooled is None:
                    scale = self._metres_per_turn[i]
                    feedback.length = self._offsets[i] + pos * scale
                    feedback.rate = vel * scale
                else:  # the drum's radius follows the length (cdpr.spool)
                    feedback.length = length = spooled.length(pos)
                    feedback.rate = spooled.rate(vel, length)
                    self._torque_per_newton[i] = spooled.motor_torque(1.0, length)
                feedback.stamp = now
                feedback.count += 1
                self.counters.accepted += 1
                return i
            if cmd is Cmd.HEARTBEAT:
                self._on_heartbeat(i, decode_heartbeat(message), now)
            elif is_error_request(message):
                self.ignored += 1  # another host asking this node
                return None
            else:
                self.drive_errors[i] = decode_error_status(message)
        except OdriveFrameError as exc:
            self.counters.reject(exc.reason)
            return None
        self.counters.accepted += 1
        return None

    def _on_heartbeat(self, i: int, heartbeat: Heartbeat, now: float) -> None:
        error = heartbeat.axis_error
        state = heartbeat.axis_state
        self._axis_state[i] = state
        self._axis_error[i] = error
        if state is self._requested[i]:
            self._requested_at[i] = -math.inf  # reached: any other state shown later is news
        elif now - self._requested_at[i] >= self._heartbeat_period:
            # refused, or left since: ask again if needed.  A heartbeat that arrived within
            # a heartbeat period of the request may have been sent before the drive took
            # it: taken as a refusal, a braked axis being enabled went back on its brake
            self._requested[i] = None
        status = self.status[i]
        status.heartbeat_stamp = now
        status.fault_code = error
        node = self.nodes[i]
        if error:
            status.fault = f"ODrive node {node}: axis error 0x{error:08X} ({error_text(error)})"
        elif not isinstance(state, AxisState):
            status.fault = f"ODrive node {node}: unknown axis state {state} (not in firmware 0.6)"
        else:
            status.fault = None
        self._refresh(i)
        if self.intent[i] in (Intent.HOLD_POSITION, Intent.HOLD_BRAKE):
            status.held, status.hold_problem = self._holds(i, state, error)

    def _holds(self, i: int, state: AxisState | int, error: int) -> tuple[bool, str | None]:
        """Whether axis i holds its cable as its heartbeat shows it (state, error): in
        closed loop for a position hold (its control mode no CANSimple frame reports:
        keepalive asks for position control again every feed period), IDLE with the
        holding brake engaged; the reason where it does not."""
        node = self.nodes[i]
        if state is AxisState.IDLE and self.has_holding_brake:
            return True, None
        if error:
            return False, f"ODrive node {node}: axis error 0x{error:08X} disarmed it, no brake"
        if self.intent[i] is Intent.HOLD_POSITION and state is AxisState.CLOSED_LOOP_CONTROL:
            return True, None
        return False, (
            f"ODrive node {node}: {_state_name(state)}, not its hold (asked for it again)"
        )

    def _refresh(self, i: int) -> None:
        """status[i].state from the last heartbeat and what the host asked for."""
        state = self._axis_state[i]
        intent = self.intent[i]
        holding = intent in (Intent.HOLD_POSITION, Intent.HOLD_BRAKE)
        if state is None or state is AxisState.UNDEFINED:
            drive_state = DriveState.UNKNOWN
        elif self._axis_error[i] or not isinstance(state, AxisState):
            drive_state = DriveState.FAULT
        elif state is AxisState.IDLE:
            drive_state = (
                DriveState.HOLDING if holding and self.has_holding_brake else DriveState.READY
            )
        elif state is AxisState.CLOSED_LOOP_CONTROL:
            drive_state = DriveState.HOLDING if holding else DriveState.ENABLED
        else:
            drive_state = DriveState.DISABLED  # a calibration or startup procedure runs
        self.status[i].state = drive_state


def _state_name(state: AxisState | int) -> str:
    return state.name if isinstance(state, AxisState) else f"unknown axis state {state}"


def _decodes(i: int, message: can.Message) -> bool:
    """Any well-formed heartbeat or estimate (a malformed one raises OdriveFrameError)."""
    if message.arbitration_id & 0x1F == Cmd.HEARTBEAT:
        decode_heartbeat(message)
    else:
        decode_encoder_estimates(message)
    return True
