"""The safety state machine and its brake triggers (DESIGN §9), pure logic.

States: INIT → IDLE (drives holding, brakes on) → HOLD (enabled, holding a pose) →
TRACKING → HOLD …; any fault → BRAKED; leaving BRAKED needs every fault condition gone
AND an explicit reset, which lands in IDLE.  PRETENSION (IDLE or BRAKED → HOLD) winds
slack cables in and tensions them before the position loop closes (cdpr.pretension).
The service asks `check_*` every cycle and brakes on the first Fault returned; each
Fault carries one readable line naming the trigger and the values.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from cdpr import Robot
from cdpr.controller import ControlOutput
from daemon.config import DaemonConfig
from drivers.base import DriveState, Feedback, NodeStatus


class SafetyState(enum.Enum):
    INIT = "init"
    IDLE = "idle"
    HOLD = "hold"
    TRACKING = "tracking"
    BRAKED = "braked"
    PRETENSION = "pretension"  # winding slack cables in, tensioning them (cdpr.pretension)


class Trigger(enum.Enum):
    """Why the daemon braked; the names appear in logs, events and state."""

    OUT_OF_WORKSPACE = "out_of_workspace"  # wrench not in W
    POSE_LIMIT = "pose_limit"
    LENGTH_LIMIT = "length_limit"
    TRACKING_ERROR = "tracking_error"
    FK_RESIDUAL = "fk_residual"
    IMPLAUSIBLE_FEEDBACK = "implausible_feedback"  # a drive's length or rate not trusted
    STALE_FEEDBACK = "stale_feedback"
    DRIVE_FAULT = "drive_fault"
    HEARTBEAT_LOST = "heartbeat_lost"
    BUS_ERROR = "bus_error"  # too many bus errors, or bus-off
    BUS_LOST = "bus_lost"  # the bus is gone: brake, then exit for a restart
    NAN = "nan"
    CONTROLLER_EXCEPTION = "controller_exception"
    SIGTERM = "sigterm"
    COMMAND = "command"  # a client asked to brake
    STARTUP = "startup"  # the drives did not come up
    COMPANION_LOST = "companion_lost"  # no companion process for safety.companion_lost s
    PAYLOAD_LIMIT = "payload_limit"  # the payload estimate beyond controller.adaptation
    PRETENSION = "pretension"  # pretension aborted: a cable not taut, the platform moved
    # the external wrench estimate beyond controller.disturbance_observer's bounds
    EXTERNAL_WRENCH = "external_wrench"


@dataclass(frozen=True)
class Fault:
    trigger: Trigger
    message: str

    def line(self) -> str:
        return f"BRAKE [{self.trigger.value}] {self.message}"


# the transitions a command may make; faults go to BRAKED from anywhere
_ALLOWED = {
    "enable": {SafetyState.IDLE},
    "disable": {SafetyState.HOLD, SafetyState.TRACKING},
    "track": {SafetyState.HOLD, SafetyState.TRACKING},
    "hold": {SafetyState.HOLD, SafetyState.TRACKING},
    "finish": {SafetyState.TRACKING},
    "reset": {SafetyState.BRAKED},
    "started": {SafetyState.INIT},
    "pretension": {SafetyState.IDLE, SafetyState.BRAKED},
    "tensioned": {SafetyState.PRETENSION},
}
_TARGET = {
    "enable": SafetyState.HOLD,
    "disable": SafetyState.IDLE,
    "track": SafetyState.TRACKING,
    "hold": SafetyState.HOLD,
    "finish": SafetyState.HOLD,
    "reset": SafetyState.IDLE,
    "started": SafetyState.IDLE,
    "pretension": SafetyState.PRETENSION,
    "tensioned": SafetyState.HOLD,
}


class TransitionError(RuntimeError):
    """A command not allowed in the current state (the message says which state)."""


@dataclass
class StateMachine:
    """The states and their transitions; `fault` remembers why it braked."""

    state: SafetyState = SafetyState.INIT
    fault: Fault | None = None
    history: list[tuple[SafetyState, SafetyState, str]] = field(default_factory=list)

    def go(self, action: str) -> SafetyState:
        """Apply `action` (enable, disable, track, hold, finish, reset, started)."""
        if self.state not in _ALLOWED[action]:
            allowed = ", ".join(sorted(s.value for s in _ALLOWED[action]))
            raise TransitionError(
                f"cannot {action} while {self.state.value} (allowed from: {allowed})"
            )
        return self._move(_TARGET[action], action)

    def brake(self, fault: Fault, supersede: bool = False) -> bool:
        """Enter BRAKED for `fault`; False if already braked: the first fault stays,
        unless `supersede` (a fault the daemon exits for, such as a lost bus, replaces
        the one on record, which was most likely its first symptom)."""
        if self.state is SafetyState.BRAKED and (not supersede or self.fault == fault):
            return False
        self.fault = fault
        self._move(SafetyState.BRAKED, fault.trigger.value)
        return True

    def pretension(self) -> SafetyState:
        """Begin pretension: from IDLE, or from BRAKED (slack cables fit no pose, which
        brakes at start-up), the fault on record then cleared; "tensioned" ends it in HOLD."""
        state = self.go("pretension")
        self.fault = None
        return state

    def reset(self, active: Sequence[Fault]) -> SafetyState:
        """Leave BRAKED for IDLE, only when no fault condition is active."""
        if active:
            raise TransitionError(
                "cannot reset while faults persist: " + "; ".join(f.message for f in active)
            )
        state = self.go("reset")
        self.fault = None
        return state

    def _move(self, target: SafetyState, why: str) -> SafetyState:
        self.history.append((self.state, target, why))
        del self.history[:-100]
        self.state = target
        return target

    @property
    def moving(self) -> bool:
        """True while the controller commands force (HOLD or TRACKING)."""
        return self.state in (SafetyState.HOLD, SafetyState.TRACKING)

    @property
    def powered(self) -> bool:
        """True while the drives follow the daemon's forces (moving, or pretension)."""
        return self.moving or self.state is SafetyState.PRETENSION


STALE_HISTORY = 1.0  # s of cycles whose missed feedback a brake reports


class SafetyMonitor:
    """The per-cycle brake triggers, configured from the daemon config."""

    def __init__(self, config: DaemonConfig) -> None:
        self.robot: Robot = config.robot
        self.limits = config.safety
        self.heartbeat_timeout = config.drives.heartbeat_timeout
        self.pose_limits = config.pose_limits
        self.stale = [0] * config.robot.n_cables
        # which drives missed their feedback in each of the last second's cycles (a bit
        # per drive), and in how many of them: a brake names them (`missed_feedback`)
        self._missed = [0] * max(1, round(config.controller.rate_hz * STALE_HISTORY))
        self._missed_at = 0
        self._missed_counts = [0] * config.robot.n_cables
        # the length limits as plain floats, for the per-cycle test (`_length_violations`)
        self._length_bounds = list(
            zip(self.robot.length_min.tolist(), self.robot.length_max.tolist(), strict=True)
        )
        self._error_stamps: deque[float] = deque()  # of the bus errors, oldest first
        self._last_error = ""
        self._bus_off: tuple[float, str] = (-math.inf, "")  # when, what
        self.lost: Fault | None = None  # the bus is gone (for good)
        # |position| (m) and |orientation| (rad) of the tracking error check_output judged
        self.tracking_errors = (0.0, 0.0)

    # -- inputs every cycle --------------------------------------------------------

    def check_drives(
        self,
        feedback: Sequence[Feedback],
        status: Sequence[NodeStatus],
        now: float,
        powered: bool = False,
    ) -> list[Fault]:
        """Drive faults, heartbeat loss, NaN feedback and length limits; with `powered`
        (the daemon commands forces), a drive whose power stage is off: another node
        disarmed it (an ODrive axis asked for IDLE), it no longer follows the forces."""
        faults = []
        timeout, isfinite = self.heartbeat_timeout, math.isfinite
        lengths = []  # the finite lengths of the drives that reported any
        for k, (fb, st) in enumerate(zip(feedback, status, strict=True)):
            if st.state is DriveState.FAULT:
                faults.append(
                    Fault(
                        Trigger.DRIVE_FAULT,
                        f"drive {k} reports fault 0x{st.fault_code:04x}: {st.fault or 'unknown'}",
                    )
                )
            elif powered and st.state in _UNPOWERED:
                faults.append(
                    Fault(
                        Trigger.DRIVE_FAULT,
                        f"drive {k} is {st.state.value} while it should follow forces "
                        "(another node changed its state?)",
                    )
                )
            age = now - st.heartbeat_stamp
            if age > timeout:
                heard = (
                    "never heard" if math.isinf(age) else f"last heartbeat {age * 1e3:.0f} ms ago"
                )
                faults.append(
                    Fault(
                        Trigger.HEARTBEAT_LOST,
                        f"drive {k}: {heard} (timeout {timeout * 1e3:.0f} ms)",
                    )
                )
            if not fb.count:
                continue
            length = fb.length
            if not (isfinite(length) and isfinite(fb.rate)):
                faults.append(
                    Fault(Trigger.NAN, f"drive {k} feedback length {length}, rate {fb.rate}")
                )
            if isfinite(length):
                lengths.append(length)
        if len(lengths) == len(feedback):  # NaN is reported above, not as a length
            problems = self._length_violations(lengths)
            if problems:
                faults.append(Fault(Trigger.LENGTH_LIMIT, "; ".join(problems)))
        return faults

    def _length_violations(self, lengths: list[float]) -> list[str]:
        """Robot.length_violations (its messages), asked only when a length is outside
        its limits: the test every cycle needs, on plain floats, costs a fraction of the
        robot's (which builds an array and reads numpy scalars)."""
        for length, (low, high) in zip(lengths, self._length_bounds, strict=True):
            if not low <= length <= high:
                return self.robot.length_violations(lengths)
        return []

    def check_freshness(self, fresh: Sequence[bool]) -> Fault | None:
        """Count consecutive cycles without feedback per actuator; the fault names the
        first drive over the limit and how many others are silent with it (one silent
        drive points at it or its cable, all of them at the bus or the host)."""
        limit, over, missed = self.limits.stale_cycles, [], 0
        for k, ok in enumerate(fresh):
            self.stale[k] = 0 if ok else self.stale[k] + 1
            if not ok:
                missed |= 1 << k
            if self.stale[k] >= limit:
                over.append(k)
        self._remember_missed(missed)
        if not over:
            return None
        first = over[0]
        others = f"; drives {', '.join(map(str, over[1:]))} too" if len(over) > 1 else ""
        return Fault(
            Trigger.STALE_FEEDBACK,
            f"drive {first}: no feedback for {self.stale[first]} consecutive cycles "
            f"(limit {limit}){others}",
        )

    def _remember_missed(self, missed: int) -> None:
        """This cycle's drives without fresh feedback (bit k: drive k) in the history."""
        i = self._missed_at
        gone, self._missed[i] = self._missed[i], missed
        self._missed_at = (i + 1) % len(self._missed)
        if gone == missed:
            return
        counts = self._missed_counts
        for k in range(len(counts)):
            counts[k] += ((missed >> k) & 1) - ((gone >> k) & 1)

    def missed_feedback(self) -> list[dict[str, int]]:
        """The drives that missed their feedback in any of the last STALE_HISTORY s of
        cycles, and in how many (`drive`, `cycles`): one drive answering late leaves its
        length carried forward into forward kinematics, which a brake on tracking or
        plausibility should be read beside."""
        return [{"drive": k, "cycles": n} for k, n in enumerate(self._missed_counts) if n]

    def bus_error(self, now: float, what: str, bus_off: bool = False) -> Fault | None:
        """Record one bus error (error frame, failed send or receive); the bus fault if
        the condition of `check_bus` now holds."""
        self._error_stamps.append(now)
        self._last_error = what
        if bus_off:
            self._bus_off = (now, what)
        return self.check_bus(now)

    def bus_lost(self, what: str) -> Fault:
        """The bus is gone (`what` ended it): a fault for good."""
        if self.lost is None:
            self.lost = Fault(Trigger.BUS_LOST, f"CAN bus lost: {what}")
        return self.lost

    def check_bus(self, now: float) -> Fault | None:
        """The bus condition, the same for braking and for allowing a reset: the bus
        lost, a bus-off within the last second, or more than bus_errors_max errors
        within it.  Sporadic errors below the limit are no fault."""
        if self.lost is not None:
            return self.lost
        stamps = self._error_stamps
        while stamps and now - stamps[0] > 1.0:
            stamps.popleft()
        off_at, off_what = self._bus_off
        if now - off_at <= 1.0:
            return Fault(Trigger.BUS_ERROR, f"bus-off within the last second ({off_what})")
        limit = self.limits.bus_errors_max
        if len(stamps) > limit:
            return Fault(
                Trigger.BUS_ERROR,
                f"{self._last_error}; {len(stamps)} bus errors in the last second (limit {limit})",
            )
        return None

    def check_output(self, output: ControlOutput) -> Fault | None:
        """Controller result: FK, wrench in W, NaN, pose limits, tracking error."""
        if not output.feasible:
            reason = output.reason
            trigger = Trigger.FK_RESIDUAL if "kinematics" in reason else Trigger.OUT_OF_WORKSPACE
            if "non-finite" in reason:
                trigger = Trigger.NAN
            if reason.startswith("payload"):
                trigger = Trigger.PAYLOAD_LIMIT
            if reason.startswith("external wrench"):
                trigger = Trigger.EXTERNAL_WRENCH
            return Fault(trigger, f"{reason} (FK residual {output.fk_residual:.3g} m)")
        commands = output.commands.tolist()
        if not all(map(math.isfinite, commands)):
            return Fault(Trigger.NAN, f"non-finite force command {commands}")
        bad = self.pose_limits.violation(output.pose)
        if bad is not None:
            return Fault(Trigger.POSE_LIMIT, bad.detail)
        ex, ey, ez, rx, ry, rz = output.theta_d.tolist()
        e_pos = math.sqrt(ex * ex + ey * ey + ez * ez)
        e_rot = math.sqrt(rx * rx + ry * ry + rz * rz)
        self.tracking_errors = (e_pos, e_rot)
        if e_pos > self.limits.tracking_error_position:
            return Fault(
                Trigger.TRACKING_ERROR,
                f"position error {e_pos * 1e3:.2f} mm exceeds "
                f"{self.limits.tracking_error_position * 1e3:.2f} mm",
            )
        if e_rot > self.limits.tracking_error_orientation:
            return Fault(
                Trigger.TRACKING_ERROR,
                f"orientation error {math.degrees(e_rot):.3f} deg exceeds "
                f"{math.degrees(self.limits.tracking_error_orientation):.3f} deg",
            )
        return None


def missed_text(missed: list[dict[str, int]]) -> str:
    """`missed_feedback` for a brake's log line ("" if no drive missed any)."""
    if not missed:
        return ""
    drives = ", ".join(f"drive {m['drive']} ({m['cycles']} cycles)" for m in missed)
    return f"; feedback missed within {STALE_HISTORY:g} s: {drives}"


# drive states in which a drive produces no commanded force (its power stage is off)
_UNPOWERED = (DriveState.READY, DriveState.DISABLED, DriveState.UNKNOWN)
