"""Single-actuator rig: its time stepping against scipy's lsim of its linear model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from cdpr import Robot
from sim_bus.plant import PlantConfig
from sim_bus.plant.rig import OUTPUTS, SingleActuatorRig
from tests.conftest import load_robot

ACTUATOR_MODELS = {
    "default lag": {},
    "no lag": {"c": []},
    # third order with every kind of coefficient: k reaches l''' (q0 and q1 non-zero)
    "general": {"c": [2e-3, 1e-6], "k": [20.0, 0.5, 1e-4], "c_tilde": [1e-3]},
}
LOADS = [0.0, 5.0, 50.0, math.inf]


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot("reference8")


def rig_for(robot: Robot, load: float, **config) -> SingleActuatorRig:
    cfg = PlantConfig.model_validate({"encoder": {"counts_per_metre": None}, **config})
    return SingleActuatorRig(robot.actuators[0], load, cfg)


def respond(rig: SingleActuatorRig, inputs: np.ndarray) -> np.ndarray:
    """Outputs (OUTPUTS order, deviations from the equilibrium) with the command
    equilibrium + inputs[k] held over step k, sampled once it is applied."""
    eq = rig.equilibrium
    out = []
    for u in inputs:
        rig.set_commands([eq["command"] + u])
        s = rig.snapshot()
        out.append([s["lengths"][0], s["rates"][0], s["load_position"][0], s["tensions"][0],
                    s["forces"][0]])  # fmt: skip
        rig.step()
    return np.array(out) - np.array([eq[name] for name in OUTPUTS])


@pytest.mark.parametrize("model", ACTUATOR_MODELS)
@pytest.mark.parametrize("load", LOADS)
def test_rig_matches_lsim_of_its_linear_model(robot: Robot, model: str, load: float) -> None:
    """At h = 0.1 ms the semi-implicit Euler rig is within 2 % of each output's range of
    the exact (lsim, zero-order hold) response of the linear model with load m."""
    h = 1e-4
    rig = rig_for(robot, load, step=h, actuator=ACTUATOR_MODELS[model])
    t = np.arange(3000) * h
    u = 20.0 * np.sin(2 * np.pi * 5 * t) + 30.0 * (t >= 0.05)
    stepped = respond(rig, u)
    _, exact, _ = signal.lsim(rig.linear_system(), u, t, interp=False)
    scale = np.abs(exact).max(axis=0)
    assert scale[0] > 1e-4  # the drum really moved
    assert np.all(np.abs(stepped - exact).max(axis=0) <= 0.02 * scale + 1e-12)


@pytest.mark.parametrize("load", [0.0, 5.0, 50.0])
def test_effective_mass_is_m0_plus_the_load(robot: Robot, load: float) -> None:
    """With a stiff cable the rig is the paper's actuator with mass m = m0 + load:
    l / f_c = 1 / (m s^2 + k0 s) at low frequency; clamped, l hardly moves."""
    rig = rig_for(robot, load, cable={"stiffness": 1e9}, actuator={"c": []})
    m, k0 = robot.m0[0] + load, robot.k0[0]
    s = 2j
    assert length_per_command(rig, s) == pytest.approx(1.0 / (m * s * s + k0 * s), rel=1e-3)
    clamped = rig_for(robot, math.inf, cable={"stiffness": 1e9}, actuator={"c": []})
    assert abs(length_per_command(clamped, s)) < 1e-8


def length_per_command(rig: SingleActuatorRig, s: complex) -> complex:
    """The linear model's transfer function from f_c to l at s."""
    sys = rig.linear_system()
    G = sys.C @ np.linalg.solve(s * np.eye(sys.A.shape[0]) - sys.A, sys.B) + sys.D
    return complex(G[0, 0])


def test_friction_breaks_linearity(robot: Robot) -> None:
    """Without friction the response to 2u is twice that to u (up to the second-order
    strain term of the cable law); Coulomb friction, which the paper warns breaks
    Assumption 1, sticks small inputs and breaks superposition."""
    u = 15.0 * np.sin(2 * np.pi * 2 * np.arange(1000) * 1e-3)

    def ratio(**config) -> float:
        small = respond(rig_for(robot, 5.0, **config), u)[:, 0]
        large = respond(rig_for(robot, 5.0, **config), 2 * u)[:, 0]
        return float(np.abs(large - 2 * small).max() / np.abs(large).max())

    assert ratio() < 1e-3
    assert ratio(friction={"coulomb": 10.0}) > 0.1
    stuck = respond(rig_for(robot, 5.0, friction={"coulomb": 10.0}), np.full(500, 8.0))
    assert np.abs(stuck[:, 1]).max() == 0.0  # 8 N net force below 10 N: the drum sticks


def test_brake_locks_the_drum(robot: Robot) -> None:
    rig = rig_for(robot, 5.0)
    rig.set_brake(0, True)
    out = respond(rig, np.full(300, 200.0))
    assert np.abs(out[:, 0]).max() == 0.0
    assert np.abs(out[:, 1]).max() == 0.0


def test_commands_saturate_at_the_drive_limit(robot: Robot) -> None:
    rig = rig_for(robot, math.inf)
    rig.set_commands([-1e4])
    assert rig.commands.tolist() == [-robot.force_max[0]]


@pytest.mark.parametrize(
    ("load", "preload", "length"),
    [(-1.0, 100.0, 2.0), (math.nan, 100.0, 2.0), (5.0, -1.0, 2.0), (5.0, math.inf, 2.0),
     (5.0, 100.0, 0.0)],
)  # fmt: skip
def test_rig_rejects_bad_parameters(robot: Robot, load: float, preload: float, length) -> None:
    with pytest.raises(ValueError):
        SingleActuatorRig(robot.actuators[0], load, preload=preload, cable_length=length)
