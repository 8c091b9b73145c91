"""The experimental check of proposed gains on one winch (paper §4: stable "as verified
experimentally by loading various passive loads"): `cdprd tune --check-loads`.

With each load hung, the winch flies the proposed single-actuator law, scaled by the
effective mass m = m0 + load as on the robot (f_c = hold + m a, a the discretised PID on
e = l - l_r and the measured rate), through a step of STEP in the length reference after
the experiment's settle time; the record gives the step's settling time and overshoot,
to set against the identified model's prediction for that mass (tuning.analysis).  It
runs as an experiment (tuning.experiment): the same amplitude bound and aborts.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from cdpr import Robot
from cdpr.control_spec import ControllerSpec
from tuning.experiment import Abort, Load, Plan, Record, WinchExperiment
from tuning.gain_design import Design
from tuning.identify import Identified
from tuning.winch_tune import Request, load_of, plan_for

STEP = 5e-3  # m: the step in the length reference
BAND = 0.02  # settled: within 2 % of the step, as tuning.analysis counts it


class StepCheck(WinchExperiment):
    """The step flown with `spec`'s single-actuator law at effective mass `mass` (kg);
    the run lasts plan.settle + plan.duration."""

    def __init__(self, plan: Plan, load: Load, spec: ControllerSpec, mass: float) -> None:
        super().__init__(plan, load)
        linear = spec.linear_controller()
        self.law = linear.discretise(plan.period, 1, spec.discretisation)
        self.order = linear.order
        self.mass = mass
        self.step = min(STEP, 0.5 * plan.travel)

    def drive(self, elapsed: float, offset: float, rate: float) -> tuple[float, float]:
        plan = self.plan
        target = self.step if elapsed >= plan.settle else 0.0
        if elapsed >= plan.settle + plan.duration:
            self.done = True
        error = np.array([[offset - target], [rate]])[: self.order]
        return 0.0, self.mass * float(self.law.step(error)[0])


class CheckResult(NamedTuple):
    """One load's check: the load (kg) and effective mass (kg), the measured step's
    settling time (s; inf: not within the run) and overshoot (fraction of the step),
    the model's prediction of both, and the abort (None: it ran)."""

    load: float
    mass: float
    settling_time: float
    overshoot: float
    predicted_settling_time: float
    predicted_overshoot: float
    abort: Abort | None


def step_response(record: Record, step: float) -> tuple[float, float]:
    """Settling time (s from the step) and overshoot (fraction) of a StepCheck's record."""
    t = np.array(record.sample_t) - record.excitation_start
    error = (np.array(record.length) - record.length[0] - step) / step
    after = t >= 0.0
    t, error = t[after], error[after]
    if not len(t):
        return math.inf, math.inf
    outside = np.flatnonzero(np.abs(error) > BAND)
    if not len(outside):
        settling = 0.0
    elif outside[-1] == len(t) - 1:
        settling = math.inf
    else:
        settling = float(t[outside[-1] + 1])
    return settling, float(max(0.0, error.max()))


def step_check(
    robot: Robot, request: Request, rate_hz: float, model: Identified, design: Design, mass: float
) -> tuple[Request, StepCheck]:
    """The check of `design`'s gains with `mass` kg hanging on the request's winch: its
    request (the amplitude within half the load's weight, so the cable stays taut) and
    experiment (2 x the settling target after the step)."""
    weight = mass * float(np.linalg.norm(robot.platform.gravity))
    amplitude = min(request.amplitude, 0.5 * weight) if mass > 0.0 else request.amplitude
    hung = request._replace(
        load_mass=mass,
        clamped=False,
        amplitude=amplitude,
        excitation=amplitude,
        duration=2.0 * design.settling_target,
    )
    spec = ControllerSpec(rate_hz=rate_hz, pid=design.gains)
    plan = plan_for(robot, hung, rate_hz)
    return hung, StepCheck(plan, load_of(robot, hung), spec, model.m0 + mass)


def check_result(check: StepCheck, design: Design) -> CheckResult:
    """The measured step against the prediction of `design`'s rig at the check's mass."""
    settling, overshoot = step_response(check.record, check.step)
    if check.abort is not None:
        settling, overshoot = math.nan, math.nan
    predicted = design.rig.loop(check.mass, design.latency)
    return CheckResult(
        check.load.mass,
        check.mass,
        settling,
        overshoot,
        predicted.settling_time,
        predicted.overshoot,
        check.abort,
    )
