"""Controller configuration: the YAML/dict schema of the `controller` section.

Validated like the robot description (pydantic, errors name the key path).  The gains
are per unit mass (the single-actuator controller returns an acceleration) and are
tuned once on one actuator (DESIGN §5).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from cdpr.description import (
    FiniteFloat,
    NonNegativeFloat,
    PositiveFloat,
    StrictModel,
    validate_section,
)
from cdpr.single_actuator import LinearController, pid

MAX_COMMAND_LEAD = 0.1  # s: a command acting later than this cannot be steered by a lead
# s: the first-order lag of a drive's force behind its command, unless told (the
# simulator's default actuator; drives.force_lag for a daemon's drives)
DEFAULT_FORCE_LAG = 2e-3


class PidSpec(StrictModel):
    """a = -(ki int e + kp e + kd e'), e' low-passed with time constant derivative_filter."""

    kp: NonNegativeFloat  # 1/s^2, proportional gain per unit mass
    ki: NonNegativeFloat = 0.0  # 1/s^3, integral gain per unit mass
    kd: NonNegativeFloat = 0.0  # 1/s, derivative gain per unit mass
    derivative_filter: NonNegativeFloat = 0.0  # s, low-pass time constant of e'; 0: unfiltered


class StateSpaceSpec(StrictModel):
    """x' = A x + B [e, e', ...], a = C x + D [e, e', ...]  (DESIGN §5)."""

    A: list[list[FiniteFloat]] = Field(default_factory=list)  # n x n state matrix; empty: no states
    B: list[list[FiniteFloat]] = Field(default_factory=list)  # n x l input matrix
    C: list[FiniteFloat] = Field(default_factory=list)  # output row, n entries
    D: Annotated[list[FiniteFloat], Field(min_length=1, max_length=2)]
    """Feedthrough on [e] or [e, e']: its length l (1 or 2) is how many error derivatives
    the law reads."""

    @model_validator(mode="after")
    def _shapes(self) -> StateSpaceSpec:
        self.build()
        return self

    def build(self) -> LinearController:
        n = len(self.A)
        if any(len(row) != n for row in self.A):
            raise ValueError(f"A must be square ({n} rows)")
        if len(self.B) != n or any(len(row) != len(self.D) for row in self.B):
            raise ValueError(f"B must be {n} x {len(self.D)} (states x error derivatives)")
        if len(self.C) != n:
            raise ValueError(f"C must have {n} entries (one per state)")
        return LinearController(
            np.array(self.A, dtype=float).reshape(n, n),
            np.array(self.B, dtype=float).reshape(n, len(self.D)),
            self.C,
            [self.D],
        )


class TensionSpec(StrictModel):
    """Tension distribution: method, and the reference tension it stays near (N; default
    mid-range between t_min and force_max of each cable)."""

    method: Literal["osqp", "closed_form"] = "osqp"
    """osqp: the tensions closest to the reference (a QP solved by OSQP); closed_form:
    Pott's closed-form method, cheaper but not optimal while a bound is active."""
    reference: PositiveFloat | None = None  # N, every cable; null: (t_min + force_max) / 2
    floor: NonNegativeFloat = 5.0
    """N above t_min the distribution keeps every cable where a distribution can (down to
    t_min where none can): a winch's tension departs from its command by what its model
    leaves out, and a cable commanded at t_min dips below it (reference8's standard
    figure-eight flown in lock-step, t_min 20 N: 19.8 N at the least without a floor,
    24.5 N with 5 N)."""


MIN_ADAPTATION_TIME = 0.1  # s: a faster estimate would reach into the loop's own dynamics


class AdaptationSpec(StrictModel):
    """Online estimate of the platform's mass, centre of mass and inertia (cdpr.payload): the
    model M, mu follows it, the gains never change.  mass_min / mass_max: the platform's
    total mass (kg) the estimate may take (default 0.8x and 1.5x the robot file's); com_max:
    how far (m) the centre of mass may move from the file's; a payload beyond these is a
    fault (the daemon brakes), not an update.  inertia: estimate the inertia too, where
    rotation excites it (else it stays the file's); beyond inertia_scale_max times the
    file's, or below 1 / it, a fault.
    time_constant (s): how slowly the model follows the estimate.  frozen: keep the model
    as it is (as set, or the file's)."""

    enabled: bool = True  # estimate the payload online; false: the model is the robot file's
    frozen: bool = False  # the model stays as it is (as set, or the file's)
    mass_min: PositiveFloat | None = None  # kg, total platform mass; null: 0.8 x the file's
    mass_max: PositiveFloat | None = None  # kg, total platform mass; null: 1.5 x the file's
    com_max: PositiveFloat = 0.1  # m, how far the centre of mass may move from the file's
    inertia: bool = True  # estimate the inertia too; false: it stays the file's
    inertia_scale_max: Annotated[float, Field(gt=1.0)] = 2.0
    """The inertia may lie within this factor of the file's, either way."""
    time_constant: Annotated[float, Field(ge=MIN_ADAPTATION_TIME, le=60.0)] = 0.5
    """s: how slowly the model follows the estimate."""

    @model_validator(mode="after")
    def _mass_range(self) -> AdaptationSpec:
        low, high = self.mass_min, self.mass_max
        if low is not None and high is not None and low >= high:
            raise ValueError(f"mass_min ({low:g} kg) must lie below mass_max ({high:g} kg)")
        return self


DEFAULT_RELEASE_HZ = 16.0  # cdpr.wrench_observer: the release; 30 Hz rings up a wrong model


class DisturbanceObserverSpec(StrictModel):
    """The external wrench observer (cdpr.wrench_observer): the wrench on the platform
    that the model does not explain, estimated from its motion, enters the model's bias
    wrench so the command cancels it; the gains never change.  bandwidth_hz: the
    observer's first-order filter; release_hz: how fast an ending wrench is let go (the
    estimate would otherwise outlive a push and the platform rebound: at least
    bandwidth_hz; default 16 Hz, or bandwidth_hz if higher); force_max (N) / torque_max
    (N·m, about p): an estimate beyond either is a fault (the daemon brakes: a
    collision, a stuck platform or a push harder than a person leaning on it), never
    compensated."""

    enabled: bool = True  # estimate and cancel external wrenches; false: no observer
    bandwidth_hz: Annotated[float, Field(gt=0.0, le=50.0)] = 4.0
    """Hz, of the observer's first-order filter."""
    release_hz: Annotated[float, Field(gt=0.0, le=50.0)] | None = None
    """Hz: how fast an ending wrench is let go, at least bandwidth_hz; null: 16 Hz, or
    bandwidth_hz if higher."""
    force_max: PositiveFloat = 100.0  # N: an estimated force beyond it is a fault (brake)
    torque_max: PositiveFloat = 20.0  # N m about p: an estimated torque beyond it is a fault

    @property
    def release(self) -> float:
        """release_hz, by default DEFAULT_RELEASE_HZ or bandwidth_hz if that is higher."""
        if self.release_hz is None:
            return max(DEFAULT_RELEASE_HZ, self.bandwidth_hz)
        return self.release_hz

    @model_validator(mode="after")
    def _release_not_slower(self) -> DisturbanceObserverSpec:
        if self.release_hz is not None and self.release_hz < self.bandwidth_hz:
            raise ValueError(
                f"release_hz ({self.release_hz:g}) must be at least bandwidth_hz "
                f"({self.bandwidth_hz:g})"
            )
        return self


class ControllerSpec(StrictModel):
    """The parallel-actuator controller (paper §5).

    model_at: evaluate M, mu, Lambda, W, F at the measured (eta, phi) or at the
      reference (eta_r, phi_r) — the paper allows both.  "reference" is the default: on
      the standard trajectory set it tracks better (the cables' geometric stiffness
      stays in the loop instead of being cancelled) and it needs one kinematics pass less.
    velocity: twist from the drives' reported rates by least squares, corrected for
      cable stretch by a complementary filter of time constant velocity_filter (s)
      ("drive"), or by differentiating successive forward-kinematics poses, low-passed
      with velocity_filter ("differentiate"), for drives that report no rate.
    command_lead: how far ahead of its measurement instant a cycle's command is
      evaluated (s): the reference, the feed-forward and the model are taken for the
      middle of the interval over which the command acts (the pose error stays at the
      measurement's instant).  "auto": the measured sample-to-command latency, plus the
      drive's force lag, plus half a period (the command is held for one); 0: the
      command is evaluated for the measurement's instant (the paper's literal timing).
    adaptation: the payload estimate (AdaptationSpec, cdpr.payload).
    disturbance_observer: the external wrench observer (DisturbanceObserverSpec).
    """

    rate_hz: Annotated[float, Field(gt=0.0, le=10000.0)] = 500.0  # Hz of the control cycle
    pid: PidSpec | None = None  # the PID law (below); null: state_space, else kp 100, ki 50, kd 20
    state_space: StateSpaceSpec | None = None  # a general linear law (below) instead of pid
    discretisation: Literal["zoh", "bilinear", "euler", "backward_diff"] = "zoh"
    """How the continuous-time law is discretised at the cycle period (scipy's
    cont2discrete): zero-order hold, Tustin, forward or backward Euler."""
    model_at: Literal["measured", "reference"] = "reference"
    velocity: Literal["drive", "differentiate"] = "drive"
    velocity_filter: PositiveFloat = 0.05  # s, the velocity estimate's filter (see velocity)
    tension: TensionSpec = TensionSpec()  # the tension distribution (below)
    command_lead: float | Literal["auto"] = "auto"
    adaptation: AdaptationSpec = AdaptationSpec()
    disturbance_observer: DisturbanceObserverSpec = DisturbanceObserverSpec()

    @field_validator("command_lead", mode="before")
    @classmethod
    def _lead(cls, value: Any) -> Any:
        """One message for both forms (the union would report each separately)."""
        if value == "auto" or (type(value) in (int, float) and 0.0 <= value <= MAX_COMMAND_LEAD):
            return value
        raise ValueError(f'must be "auto" or a time in seconds from 0 to {MAX_COMMAND_LEAD:g}')

    @model_validator(mode="after")
    def _one_law(self) -> ControllerSpec:
        if self.pid is not None and self.state_space is not None:
            raise ValueError("give either pid or state_space, not both")
        return self

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    def lead(self, drive_lag: float, latency: float = 0.0) -> float:
        """The command lead (s) for a drive whose force follows its command with a
        first-order lag `drive_lag` (s), the command leaving `latency` s after the
        measurement: command_lead, or with "auto" the middle of the interval over which
        a command held for one period acts once it has arrived and the drive has
        followed it."""
        if self.command_lead == "auto":
            return latency + drive_lag + 0.5 * self.period
        return self.command_lead

    def linear_controller(self) -> LinearController:
        """The single-actuator controller (default PID if neither law is given)."""
        if self.state_space is not None:
            return self.state_space.build()
        gains = self.pid or DEFAULT_PID
        return pid(gains.kp, gains.ki, gains.kd, gains.derivative_filter)


DEFAULT_PID = PidSpec(kp=100.0, ki=50.0, kd=20.0)


def parse_controller(data: Any, source: str = "config", key: str = "controller") -> ControllerSpec:
    """Validate a plain dict; ConfigError names every bad key."""
    return validate_section(ControllerSpec, {} if data is None else data, source, key)
