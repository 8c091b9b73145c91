"""One winch's identification experiment, sans-IO: what `cdprd tune` commands each cycle.

The winch carries a passive load (the paper's §4 rig: a hanging mass, none, or the
drum clamped) and is driven in torque mode.  Every cycle the host commands

    f_c = hold + clip(u - Kp (l - l_start) - Kd l', +-amplitude)

with `hold` the force that holds the load still (-m g for a hanging mass, -preload for a
clamped drum, 0 for a free drum), u a pseudo-random binary sequence of +-excitation
(broadband: it excites the back-EMF corner, the drum's inertia and the force lag alike)
and a weak position loop (bandwidth `stabiliser_hz`) that keeps the winch near where it
started.  The command never leaves hold +- amplitude.  The fit (tuning.identify) uses the
command as sent, so the loop's share is input like the rest.

Each cycle first checks the limits and aborts, naming which, on a drive fault, a slack
cable (the drum accelerating as only an unloaded drum could under the hold force), the
length leaving the travel window or the actuator's range, or the command pinned at its
amplitude (the load is not what the user said).  The caller brakes on an abort.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from drivers.base import ActuatorDriver, DriveState, Feedback, NodeStatus

SLACK_WINDOW = 0.01  # s over which the drum's acceleration is estimated from its rates
SATURATED_FOR = 0.5  # s the stabiliser may stay pinned at the amplitude


class Abort(RuntimeError):  # noqa: N818 (an outcome, not a bug)
    """The experiment stopped: `kind` is drive_fault, slack_cable, length_limit,
    force_limit or no_feedback (or, on a bus in real time, startup or bus_lost); the
    message says what was seen."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(f"{kind.replace('_', ' ')}: {message}")
        self.kind = kind


@dataclass(frozen=True)
class Load:
    """The passive load: `mass` kg on the cable (0: none, the free drum; inf: clamped)
    and `hold`, the command (N along +l) that holds it at rest."""

    mass: float
    hold: float

    @classmethod
    def hanging(cls, mass: float, gravity: float) -> Load:
        if not 0.0 <= mass < math.inf:
            raise ValueError(f"load mass must be a finite mass >= 0 kg, got {mass}")
        return cls(mass, -mass * gravity)

    @classmethod
    def clamped(cls, preload: float) -> Load:
        if not 0.0 < preload < math.inf:
            raise ValueError(f"a clamped drum needs a pretension > 0 N, got {preload}")
        return cls(math.inf, -preload)


@dataclass(frozen=True)
class Plan:
    """Experiment settings.  amplitude: the largest |f_c - hold| ever commanded (N);
    excitation: the PRBS level (N, <= amplitude); duration: excitation time (s) after
    `settle` s of holding; travel: the largest |l - l_start| allowed (m); the actuator's
    length range and force limit; m0_guess (kg), k0_guess (N s/m): the robot file's
    values, for the stabiliser and the slack test; seed: the PRBS's; stale_cycles: as
    the daemon's safety.stale_cycles."""

    amplitude: float
    excitation: float
    duration: float
    travel: float
    length_min: float
    length_max: float
    force_max: float
    m0_guess: float
    k0_guess: float
    period: float
    settle: float = 0.5
    stabiliser_hz: float = 1.0
    prbs_hold: int = 1  # loop periods per PRBS bit
    seed: int = 0
    stale_cycles: int = 3  # cycles in a row without new feedback before no_feedback

    def check(self, load: Load) -> None:
        """ValueError naming the limit a plan breaks for `load`."""
        if not 0.0 < self.excitation <= self.amplitude:
            raise ValueError(
                f"excitation {self.excitation} N must be > 0 and within the amplitude "
                f"{self.amplitude} N"
            )
        if abs(load.hold) + self.amplitude > self.force_max:
            raise ValueError(
                f"hold {abs(load.hold):.1f} N + amplitude {self.amplitude} N exceeds the "
                f"actuator's force_max {self.force_max} N"
            )
        if load.hold and self.amplitude > 0.5 * abs(load.hold):
            raise ValueError(
                f"amplitude {self.amplitude} N exceeds half the load's {abs(load.hold):.1f} N: "
                "the cable could go slack (lower --amplitude or hang more mass)"
            )
        if not (self.duration > 0.0 and self.travel > 0.0):
            raise ValueError("duration and travel must be positive")


@dataclass
class Record:
    """What was commanded and measured: command times (s, when sent) and values (N), and
    the feedback samples (s: their receive stamps; m; m/s).  `transit` (s) is the bus's
    one-way delay where it was measured (from the feedback frames' own stamps; 0 in
    simulated time), taken to delay the commands as much on their way to the drive."""

    command_t: list[float] = field(default_factory=list)
    command: list[float] = field(default_factory=list)
    opened: list[float] = field(default_factory=list)  # s: each command's cycle opened
    sample_t: list[float] = field(default_factory=list)
    length: list[float] = field(default_factory=list)
    rate: list[float] = field(default_factory=list)
    excitation_start: float = math.nan
    hold: float = 0.0
    transit: float = 0.0

    def latencies(self) -> np.ndarray:
        """Per command, the time (s) from the later of its cycle's opening and the newest
        feedback sample before it to its sending: the loop's latency on the host's
        clock, as the daemon counts it (daemon.service.cycle_stats)."""
        stamps = np.array(self.sample_t)
        sent = np.array(self.command_t)
        newest = np.searchsorted(stamps, sent, side="right") - 1
        valid = newest >= 0
        since = np.maximum(stamps[newest[valid]], np.array(self.opened)[valid])
        return sent[valid] - since

    def arrays(self) -> dict[str, np.ndarray]:
        """The record for the fit: command_t when the commands reached the drive."""
        return {
            "command_t": np.array(self.command_t) + self.transit,
            "command": np.array(self.command),
            "sample_t": np.array(self.sample_t),
            "length": np.array(self.length),
            "rate": np.array(self.rate),
        }


class WinchExperiment:
    """The per-cycle logic: `cycle(t, feedback, status)` returns the command (N) or raises
    Abort; `sent(t, command)` records when it went out; `done` once the excitation ran.
    `forces(t, driver)` is both for drive 0 of a driver, as a cycle runs it."""

    def __init__(self, plan: Plan, load: Load) -> None:
        plan.check(load)
        self.plan, self.load = plan, load
        w = 2.0 * math.pi * plan.stabiliser_hz
        mass = plan.m0_guess + (load.mass if math.isfinite(load.mass) else 0.0)
        self.kp = mass * w * w
        self.kd = max(0.0, 2.0 * 0.7 * mass * w - plan.k0_guess)
        bits = math.ceil((plan.duration / plan.period) / plan.prbs_hold) + 1
        rng = np.random.default_rng(plan.seed)
        self._prbs = np.where(rng.random(bits) < 0.5, -1.0, 1.0) * plan.excitation
        self.slack_accel = 0.6 * abs(load.hold) / plan.m0_guess if load.hold else math.inf
        self.record = Record(hold=load.hold)
        self._t0 = math.nan
        self._start = math.nan
        self._count = -1
        self._rates: list[tuple[float, float]] = []
        self._pinned = 0
        self._stale = 0
        self.done = False
        self.abort: Abort | None = None

    def forces(
        self, t: float, driver: ActuatorDriver, opened: float | None = None
    ) -> list[float] | None:
        """The cycle at host time t (s; opened at `opened`, default t) for drive 0 of
        `driver`: its command, recorded as sent; None once the excitation ran or the
        experiment aborted (`abort` says why: the caller brakes)."""
        if self.abort is not None:
            return None
        try:
            command = self.cycle(t, driver.feedback[0], driver.status[0])
        except Abort as exc:
            self.abort = exc
            return None
        if self.done:
            return None
        self.sent(t, command, opened)
        return [command]

    def cycle(self, t: float, feedback: Feedback, status: NodeStatus) -> float:
        """The command for the cycle at host time t (s)."""
        plan = self.plan
        if status.state is DriveState.FAULT:
            raise Abort("drive_fault", f"the drive reports {status.fault or 'a fault'}")
        if feedback.count == self._count:
            self._stale += 1
            if self._stale > plan.stale_cycles:
                raise Abort("no_feedback", f"no new feedback for {self._stale} cycles")
        else:
            self._stale = 0
            self._count = feedback.count
            self._sample(feedback)
        length, rate = feedback.length, feedback.rate
        if math.isnan(self._t0):
            self._t0, self._start = t, length
        offset = length - self._start
        if abs(offset) > plan.travel or not plan.length_min <= length <= plan.length_max:
            raise Abort(
                "length_limit",
                f"length {length:.4f} m left the window {self._start:.4f} +- {plan.travel} m "
                f"(actuator range {plan.length_min}..{plan.length_max} m)",
            )
        elapsed = t - self._t0
        if elapsed >= plan.settle and math.isnan(self.record.excitation_start):
            self.record.excitation_start = t
        u, loop = self.drive(elapsed, offset, rate)
        delta = u + loop
        a = plan.amplitude
        self._pinned = self._pinned + 1 if abs(loop) > a else 0
        if self._pinned * plan.period > SATURATED_FOR:
            raise Abort(
                "force_limit",
                f"holding the winch needed more than the amplitude {a} N for "
                f"{SATURATED_FOR} s (is the load {self.load.mass:g} kg as given?)",
            )
        return self.load.hold + min(a, max(-a, delta))

    def drive(self, elapsed: float, offset: float, rate: float) -> tuple[float, float]:
        """The command's change from the hold `elapsed` s into the run, the winch
        `offset` m from where it started at `rate` m/s: (the excitation: the PRBS once
        settled; the loop's share: the stabiliser).  Sets `done` at the PRBS's end."""
        plan = self.plan
        u = 0.0
        if elapsed >= plan.settle:
            k = int((elapsed - plan.settle) / plan.period + 0.5) // plan.prbs_hold
            if k >= len(self._prbs) - 1:
                self.done = True
            u = float(self._prbs[min(k, len(self._prbs) - 1)])
        return u, -self.kp * offset - self.kd * rate

    def sent(self, t: float, command: float, opened: float | None = None) -> None:
        """`command` went out at t (s), in the cycle opened at `opened` (default t)."""
        self.record.command_t.append(t)
        self.record.command.append(command)
        self.record.opened.append(t if opened is None else opened)

    def _sample(self, fb: Feedback) -> None:
        rec = self.record
        rec.sample_t.append(fb.stamp)
        rec.length.append(fb.length)
        rec.rate.append(fb.rate)
        self._rates.append((fb.stamp, fb.rate))
        while self._rates and self._rates[0][0] < fb.stamp - SLACK_WINDOW:
            self._rates.pop(0)
        t0, v0 = self._rates[0]
        if fb.stamp - t0 >= 0.5 * SLACK_WINDOW:
            accel = (fb.rate - v0) / (fb.stamp - t0)
            if abs(accel) > self.slack_accel:
                raise Abort(
                    "slack_cable",
                    f"the drum accelerated at {accel:.1f} m/s^2, beyond the "
                    f"{self.slack_accel:.1f} m/s^2 a taut cable under the "
                    f"{abs(self.load.hold):.0f} N load allows",
                )
