"""Single-actuator gains from an identified model, checked over m in [m0, inf) (paper §4).

The family is the hand-tuned default's shape, a = -(kp e + ki int e + kd e') with
kp = w^2, kd = 2 w, ki = kp / 2 (w = 10 1/s gives the defaults 100, 50, 20): critically
damped in the rigid limit whatever the mass, since the gains are per unit mass.  The
design takes the fastest w whose sampled loop (tuning.analysis: the identified actuator
and lag, the cable, the encoder's rate, commands `latency` s late) is stable for every
mass from m0 to MASS_MARGIN times the largest modal mass of the robot (Lemma 1, as
`cdprd analyze` finds them) with twice the measured latency plus half a period (a margin),
and settles within the target at the ends of the modal-mass range.  (With an elastic
cable no PID of this kind is stable up to m = inf: the cable's mode is what limits it.)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from cdpr import Robot
from cdpr.control_spec import ControllerSpec, PidSpec
from sim_bus.plant.config import ActuatorModelConfig, CableConfig, PlantConfig
from tuning.analysis import LoopModes, Rig
from tuning.identify import Identified
from tuning.workspace_analysis import rig_for

CANDIDATES = np.geomspace(60.0, 2.0, 30)  # w (1/s), fastest first
SWEEP_MASSES = 16
MASS_MARGIN = 1.5


class Design(NamedTuple):
    """The proposed gains, the loops they give at the masses checked (poles, settling),
    and whether every check passed."""

    gains: PidSpec
    bandwidth: float  # w (1/s)
    sweep: tuple[LoopModes, ...]  # m0 .. MASS_MARGIN x the largest modal mass
    modal: tuple[LoopModes, ...]  # at the modal-mass range's ends
    latency: float
    settling_target: float
    ok: bool
    rig: Rig  # the identified winch's rig with these gains (Rig.loop predicts a load)

    def controller_section(self, rate_hz: float) -> dict[str, object]:
        """The `controller:` section for the config (gains per unit mass)."""
        return {"rate_hz": rate_hz, "pid": self.gains.model_dump()}


def identified_robot(robot: Robot, model: Identified) -> Robot:
    """`robot` with the identified m0 and k0 for every winch (the paper: one actuator's
    model stands for all)."""
    spec = robot.spec.model_dump(exclude_none=True)
    for actuator in [spec["actuator"]] + [c["actuator"] for c in spec["cables"]]:
        actuator.update({"m0": model.m0, "k0": model.k0})
    return Robot.from_dict(spec, source=f"{robot.name} with the identified actuator")


def identified_plant(robot: Robot, model: Identified) -> PlantConfig:
    """The analysis's plant model of the identified winch: its force lag, the robot
    file's cable stiffness (else the simulator's) and the fitted cable damping (else
    the simulator's)."""
    return PlantConfig(
        actuator=ActuatorModelConfig(c=[model.lag]),
        cable=CableConfig(
            stiffness=robot.actuators[0].cable_stiffness or PlantConfig().cable.stiffness,
            damping=model.cable_damping or PlantConfig().cable.damping,
        ),
    )


def family(w: float) -> PidSpec:
    return PidSpec(kp=w * w, ki=0.5 * w * w, kd=2.0 * w)


def design(
    robot: Robot,
    model: Identified,
    modal_range: tuple[float, float],
    latency: float,
    rate_hz: float = 500.0,
    settling_target: float = 5.0,
) -> Design:
    """The fastest gains of the family that pass every check (module docstring); the
    slowest candidate, ok False, if none does."""
    spec = ControllerSpec(rate_hz=rate_hz, pid=family(10.0))
    base = rig_for(identified_robot(robot, model), spec, identified_plant(robot, model))
    lo, hi = max(model.m0, modal_range[0]), max(model.m0, modal_range[1])
    masses = np.geomspace(model.m0, MASS_MARGIN * hi, SWEEP_MASSES)
    result = None
    for w in CANDIDATES:
        gains = family(float(w))
        rig = base._replace(
            controller=ControllerSpec(rate_hz=rate_hz, pid=gains).linear_controller()
        )
        result = _check(rig, gains, float(w), masses, (lo, hi), latency, settling_target)
        if result.ok:
            return result
    assert result is not None
    return result


def _check(
    rig: Rig,
    gains: PidSpec,
    w: float,
    masses: np.ndarray,
    modal: tuple[float, float],
    latency: float,
    target: float,
) -> Design:
    margin = all(rig.stable(float(m), 2.0 * latency + 0.5 * rig.period) for m in masses)
    sweep = tuple(rig.loop(float(m), latency) for m in masses) if margin else ()
    modal_loops = tuple(rig.loop(float(m), latency) for m in modal) if margin else ()
    ok = (
        margin
        and all(loop.stable for loop in sweep)
        and all(loop.settling_time <= target for loop in modal_loops)
    )
    return Design(gains, w, sweep, modal_loops, latency, target, ok and math.isfinite(w), rig)
