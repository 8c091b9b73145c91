"""Plant physics: statics, energy, slack, brakes, breakage, conventions shared with cdpr.

Tolerances are physical: 0.1 mm / 0.01 deg for holding; energy drift relative to the
energy put into the motion (not to the arbitrary zero of gravity potential).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.optimize import least_squares

from cdpr import ConfigError, Pose, Robot, liediff, retract
from cdpr.so3 import quat_to_r9
from sim_bus.plant import (
    ActuatorModelConfig,
    Plant,
    PlantConfig,
    equilibrium_tensions,
    parse_plant_config,
)
from tests.conftest import load_robot
from tuning.lockstep import run_lockstep

ZERO_TWIST = np.zeros(6)
KICK = np.array([0.05, -0.03, 0.02, 0.1, 0.05, -0.08])  # m/s, rad/s


@pytest.fixture(scope="module")
def suspended6() -> Robot:
    return load_robot("suspended6")


@pytest.fixture(scope="module")
def reference8() -> Robot:
    return load_robot("reference8")


def tilted(robot: Robot) -> Pose:
    """An asymmetric pose: offset and tilted, so the centre-of-mass torque matters."""
    return Pose.from_rotvec(robot.home.position + np.array([0.12, -0.07, 0.1]), [0.05, -0.04, 0.08])


def config(**data) -> PlantConfig:
    return PlantConfig.model_validate(data)


def deviation(reference: Pose, pose: Pose) -> tuple[float, float]:
    """(max position error in m, rotation error in deg)."""
    d = liediff(reference, pose)
    return float(np.abs(d[:3]).max()), math.degrees(float(np.linalg.norm(d[3:])))


def worst_deviation(plant: Plant, reference: Pose, seconds: float) -> tuple[float, float]:
    worst = (0.0, 0.0)
    for _ in range(round(seconds / plant.config.step)):
        plant.step()
        worst = tuple(
            max(a, b) for a, b in zip(worst, deviation(reference, plant.pose), strict=True)
        )
    return worst


# -- configuration ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        ({"actuator": {"c": [1e-3, 1e-6, 1.0]}}, "actuator.c: 1 + c[0] s"),
        ({"actuator": {"c": [-1e-3]}}, "actuator.c.0: Input should be greater than or equal"),
        ({"actuator": {"c": [1e-3], "k": [1.0, 2.0, 3.0, 4.0]}}, "actuator: k has 4"),
        ({"actuator": {"c": [], "c_tilde": [1e-3]}}, "actuator: c_tilde has 1"),
        ({"cable": {"stiffness": 0}}, "cable.stiffness: Input should be greater than 0"),
        ({"encoder": {"latency_steps": -1}}, "encoder.latency_steps"),
        ({"frction": {}}, "frction: Extra inputs are not permitted"),
        ({"substeps": 0}, "substeps: Input should be greater than or equal to 1"),
    ],
)
def test_config_errors_name_the_key(data: dict, expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_plant_config(data)
    assert expected in str(info.value)


def test_anchor_offsets_must_match_the_cables(reference8: Robot) -> None:
    with pytest.raises(ConfigError, match=r"mismatch\.anchor_offsets: 2 entries for 8 cables"):
        Plant(reference8, config(mismatch={"anchor_offsets": [[0, 0, 0]] * 2}))


def test_mismatch_builds_the_true_robot_with_cdpr(reference8: Robot) -> None:
    offsets = np.zeros((8, 3))
    offsets[2] = [0.01, -0.02, 0.005]
    cfg = config(
        seed=3,
        mismatch={
            "mass_scale": 1.1,
            "inertia_scale": 0.9,
            "m0_scale": 1.2,
            "k0_scale": 0.5,
            "center_of_mass_offset": [0.0, 0.01, 0.0],
            "anchor_offsets": offsets.tolist(),
            "anchor_error_std": 1e-3,
        },
    )
    plant = Plant(reference8, cfg)
    true = plant.robot
    assert plant.model is reference8
    assert true.platform.mass == pytest.approx(11.0)
    np.testing.assert_allclose(true.platform.inertia, 0.9 * reference8.platform.inertia)
    np.testing.assert_allclose(true.m0, 1.2 * reference8.m0)
    np.testing.assert_allclose(true.k0, 0.5 * reference8.k0)
    np.testing.assert_allclose(true.platform.center_of_mass, [0.0, 0.01, -0.02])
    error = true.geometry.anchors - reference8.geometry.anchors - offsets
    assert 1e-4 < np.abs(error).max() < 5e-3  # the random part, about 1 mm
    # seeded: the same errors again, other errors with another seed
    again = Plant(reference8, cfg).robot.geometry.anchors
    np.testing.assert_array_equal(again, true.geometry.anchors)
    other = Plant(reference8, cfg.model_copy(update={"seed": 4})).robot.geometry.anchors
    assert np.abs(other - true.geometry.anchors).max() > 1e-5
    # the model is untouched
    assert reference8.platform.mass == 10.0


# -- the actuator model -------------------------------------------------------------------


def from_roots(real: list[float], pair: tuple[float, float] | None = None) -> list[float]:
    """Coefficients (c_2, c_3, ...) of 1 + c_2 s + ... with real roots at -r for r in
    `real` and, for pair = (w, zeta), a complex pair of frequency w and damping zeta."""
    poly = np.array([1.0])
    for r in real:
        poly = np.polynomial.polynomial.polymul(poly, [1.0, 1.0 / r])
    if pair is not None:
        w, zeta = pair
        poly = np.polynomial.polynomial.polymul(poly, [1.0, 2 * zeta / w, 1 / w**2])
    return poly[1:].tolist()


frequencies = st.lists(st.floats(50.0, 5000.0), max_size=2)  # rad/s


@given(
    poles=frequencies,
    pair=st.none() | st.tuples(st.floats(100.0, 3000.0), st.floats(0.1, 1.0)),
    zeros=frequencies,
    k=st.lists(st.floats(0.0, 30.0), min_size=1, max_size=7),
    omega=st.floats(0.1, 1e4),
)
def test_realisation_satisfies_assumption_1(poles, pair, zeros, k, omega) -> None:
    """C(s) f = C~(s) f_c - K(s) l for the realised transfer functions f/f_c and f/l,
    on the imaginary axis s = jω, for stable actuators (poles in the left half plane)
    whose f_c enters with at most as many derivatives as f (orders up to 4: the
    companion-form realisation loses digits beyond that)."""
    s = 1j * omega
    c = from_roots(poles, pair)
    c_tilde = from_roots(zeros[: len(c)])
    k = k[: len(c) + 2]
    data = {"actuator": {"c": c, "k": k, "c_tilde": c_tilde}}
    # the instantaneous viscous part q0 of f/l': refused when negative (not passive)
    quotient = np.polynomial.polynomial.polydiv(k, [1.0, *c])[0]
    if quotient[0] < -1e-9:
        with pytest.raises(ConfigError, match=r"actuator: k .* q0 = .* < 0"):
            parse_plant_config(data)
        return
    model = parse_plant_config(data).actuator.model(0.0)
    poly = np.polynomial.polynomial.polyval
    G = model.C @ np.linalg.solve(s * np.eye(model.order) - model.A, model.B) + model.D
    f_per_fc = G[0, 0]
    # f_in = G_fc f_c + G_v s l, and f = f_in - q0 s l - q1 s^2 l
    f_per_l = G[0, 1] * s - model.q0 * s - model.q1 * s * s
    C = poly(s, [1.0, *c])
    assert C * f_per_fc == pytest.approx(poly(s, [1.0, *c_tilde]), rel=1e-6)
    K = poly(s, [0.0, *k])
    # f/l is a difference of terms that can be far larger than it: allow their rounding
    terms = abs(C) * (abs(G[0, 1] * s) + abs(model.q0 * s) + abs(model.q1 * s * s))
    assert C * f_per_l == pytest.approx(-K, rel=1e-6, abs=1e-12 * terms + 1e-12)


def test_default_actuator_is_a_lag_with_back_emf() -> None:
    model = ActuatorModelConfig().model(20.0)
    # tau_e f' + f = f_c - k0 l'
    np.testing.assert_allclose(model.A, [[-500.0]])
    np.testing.assert_allclose(model.B, [[500.0, -10_000.0]])
    assert (model.q0, model.q1, model.back_emf) == (0.0, 0.0, 20.0)


# -- statics ------------------------------------------------------------------------------


def test_equilibrium_tensions_balance_gravity(robot: Robot) -> None:
    for pose in (robot.home, tilted(robot)):
        t = equilibrium_tensions(robot, pose)
        assert np.all(t >= robot.t_min - 1e-9)
        np.testing.assert_allclose(
            -robot.jacobian(pose).T @ t, robot.bias_wrench(pose, ZERO_TWIST), atol=1e-9
        )


def test_equilibrium_tensions_keep_t_min(reference8: Robot) -> None:
    """With a low reference the closed form breaks t >= t_min; the QP keeps it, some
    cables at exactly t_min."""
    pose = tilted(reference8)
    t = equilibrium_tensions(reference8, pose, reference=0.0)
    assert np.all(t >= reference8.t_min - 1e-9)
    assert np.sum(t < reference8.t_min + 1e-6) >= 2
    np.testing.assert_allclose(
        -reference8.jacobian(pose).T @ t, reference8.bias_wrench(pose, ZERO_TWIST), atol=1e-9
    )


def test_equilibrium_tensions_refuse_an_impossible_pose(suspended6: Robot) -> None:
    # far outside the triangle of posts, gravity cannot be held by pulling cables
    pose = Pose(suspended6.home.position + np.array([2.5, 0.0, 0.0]))
    with pytest.raises(ValueError, match="no tensions >= t_min hold"):
        equilibrium_tensions(suspended6, pose)


def test_reset_is_an_equilibrium(robot: Robot) -> None:
    pose = tilted(robot)
    t = equilibrium_tensions(robot, pose)
    plant = Plant(robot, config(encoder={"counts_per_metre": None}))
    plant.reset(pose, t)
    np.testing.assert_allclose(plant.tensions, t, rtol=1e-12)
    np.testing.assert_allclose(plant.forces, -t, rtol=1e-12)
    np.testing.assert_allclose(plant.commands, -t, rtol=1e-12)
    # the paper's t = f0 - f, with f0 = m0 l'' = 0 at rest
    plant.step()
    assert np.abs(plant.twist).max() < 1e-12
    assert np.abs(plant.drum_rates).max() < 1e-12
    lengths, _ = plant.measure()
    np.testing.assert_allclose(lengths, plant.drum_lengths, atol=1e-15)
    # stretched cables: the drums paid out L / (1 + t / EA)
    EA = plant.config.cable.stiffness
    np.testing.assert_allclose(plant.cable_lengths / plant.drum_lengths, 1 + t / EA, rtol=1e-12)


def test_static_hold_open_loop(suspended6: Robot) -> None:
    """Constant commands f = -t from the model hold the suspended robot: 0.1 mm, 0.01 deg.

    A 1 um/s kick keeps the check honest: an exact equilibrium can otherwise sit still
    only because updates below one ulp of the position are lost."""
    for pose in (suspended6.home, tilted(suspended6)):
        t = equilibrium_tensions(suspended6, pose)
        plant = Plant(suspended6)
        plant.reset(pose, t, twist=1e-5 * KICK)
        plant.set_commands(-t)
        position, angle = worst_deviation(plant, pose, 5.0)
        assert position < 1e-4
        assert angle < 0.01


def test_constant_forces_cannot_hold_the_crossed_robot(reference8: Robot) -> None:
    """Physics the controller must live with: under its internal pretension the crossed
    8-cable robot has a negative geometric stiffness, so constant winch forces (no
    position feedback) leave the equilibrium exponentially (about e^4/s here)."""
    pose = tilted(reference8)
    t = equilibrium_tensions(reference8, pose)
    plant = Plant(reference8)
    plant.reset(pose, t, twist=1e-5 * KICK)
    plant.set_commands(-t)
    position, angle = worst_deviation(plant, pose, 3.0)
    assert position > 1e-3 or angle > 1.0


def test_static_hold_with_drum_position_loop(reference8: Robot) -> None:
    """Forces from the model plus a drive-level position loop on the encoder lengths
    hold the crossed robot at its model equilibrium within 0.1 mm, 0.01 deg for 5 s."""
    for pose in (reference8.home, tilted(reference8)):
        t = equilibrium_tensions(reference8, pose)
        plant = Plant(reference8)  # default encoders: 10 um counts
        plant.reset(pose, t, twist=1e-5 * KICK)
        hold, _ = plant.measure()

        def controller(_t, lengths, rates, t=t, hold=hold):
            return -t - 2e4 * (lengths - hold) - 400.0 * rates

        rec = run_lockstep(plant, controller, 5.0, 1000)
        errors = np.array([deviation(pose, rec.pose(i)) for i in range(len(rec))])
        assert errors[:, 0].max() < 1e-4
        assert errors[:, 1].max() < 0.01


# -- energy -------------------------------------------------------------------------------

CONSERVATIVE = {"cable": {"damping": 0.0}, "actuator": {"k": [0.0]}}


def energy_series(plant: Plant, seconds: float, braked: bool) -> tuple[np.ndarray, float]:
    """Energy every step, and the energy put in by the kick (over the rest state).

    Free drums under constant forces f: E = mechanical energy - f.l + W, where
    W = ∫ t ε/2 dl is the energy the cable law t = EA ε (ε = (L - l)/l, equal tension
    at both ends) exchanges as cable is paid out; it is second order in the strain."""
    f = plant.forces

    def energy() -> float:
        return plant.energy() - (0.0 if braked else float(f @ plant.drum_lengths))

    rest = Plant(plant.model, plant.config)
    rest.reset(plant.pose, plant.tensions)
    rest_energy = rest.energy() - (0.0 if braked else float(f @ rest.drum_lengths))
    plant.reset(plant.pose, plant.tensions, twist=KICK)
    if braked:
        plant.set_brake(None, True)
    plant.set_commands(f)
    series = []
    flow = 0.0
    for _ in range(round(seconds / plant.config.step)):
        tensions, lengths = plant.tensions, plant.drum_lengths
        strain = (plant.cable_lengths - lengths) / lengths
        plant.step()
        flow += float(np.sum(0.5 * tensions * strain * (plant.drum_lengths - lengths)))
        series.append(energy() + flow)
    return np.array(series), series[0] - rest_energy


@pytest.mark.parametrize(("name", "braked"), [("suspended6", False), ("reference8", True)])
def test_energy_is_conserved(name: str, braked: bool) -> None:
    """No damping, friction or back-EMF: the energy of the motion does not drift.

    Drift is the change of the 1 s mean between the first and the last second (the
    semi-implicit Euler energy oscillates by O(h ω) around a conserved value), relative
    to the energy of the motion; the crossed robot runs braked, as its constant-force
    equilibrium is unstable (see above)."""
    plant = Plant(load_robot(name), config(**CONSERVATIVE))
    energy, excitation = energy_series(plant, 10.0, braked)
    assert excitation > 0.01  # J: a real motion
    window = round(1.0 / plant.config.step)
    drift = abs(energy[-window:].mean() - energy[:window].mean())
    assert drift < 1e-3 * excitation
    assert np.abs(energy - energy[0]).max() < 0.1 * excitation


def test_damping_dissipates(suspended6: Robot) -> None:
    plant = Plant(suspended6)
    energy, excitation = energy_series(plant, 2.0, braked=False)
    assert energy[-1] < energy[0] - 0.1 * excitation


# -- slack, brakes, breakage ---------------------------------------------------------------


@pytest.mark.parametrize("released", [3, 5])  # others make a second cable go slack too
def test_released_cable_goes_slack_and_the_rest_hold(reference8: Robot, released: int) -> None:
    """Brakes on every other winch, drive `released` off: its cable goes slack for good and
    the platform settles where the remaining braked elastic cables and gravity balance
    (solved here from cdpr's lengths, Λ and μ)."""
    pose = tilted(reference8)
    plant = Plant(reference8, config(cable={"damping": 1000.0}))
    plant.reset(pose, equilibrium_tensions(reference8, pose))
    plant.set_brake(None, True)
    plant.release(released)
    slack_since = None
    for i in range(3000):
        plant.step()
        assert plant.tensions.min() >= 0.0  # cables only pull
        if plant.tensions[released] == 0.0:
            slack_since = i if slack_since is None else slack_since
        else:
            assert slack_since is None, "the released cable took load again"
    assert slack_since is not None and slack_since < 100

    lengths = plant.drum_lengths
    EA = plant.config.cable.stiffness
    keep = np.arange(8) != released

    def residual(x: np.ndarray) -> np.ndarray:
        eta = retract(pose, x)
        L, Lam = reference8.lengths_and_jacobian(eta)
        t = np.where(keep, EA * np.maximum(L - lengths, 0.0) / lengths, 0.0)
        return Lam.T @ t + reference8.bias_wrench(eta, ZERO_TWIST)

    solution = least_squares(residual, np.zeros(6), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    predicted = retract(pose, solution.x)
    assert np.abs(solution.fun).max() < 1e-8
    assert deviation(pose, predicted)[0] > 3e-3  # it really moved
    position, angle = deviation(predicted, plant.pose)
    assert position < 1e-6
    assert angle < 1e-4


@pytest.mark.parametrize("speed", [0.0, 1.0])
def test_brakes_hold_under_gravity(reference8: Robot, speed: float) -> None:
    """Drives off, brakes on (also when engaged during motion): the platform stays, or
    comes back, within 0.1 mm / 0.01 deg of where the locked cable lengths put it."""
    pose = tilted(reference8)
    plant = Plant(reference8, config(cable={"damping": 1000.0}))
    plant.reset(pose, equilibrium_tensions(reference8, pose), twist=speed * KICK)
    plant.set_brake(None, True)
    plant.set_commands(np.zeros(8))
    plant.advance(3.0)
    assert np.abs(plant.drum_rates).max() == 0.0
    position, angle = deviation(pose, plant.pose)
    assert position < 1e-4
    assert angle < 0.01
    # without the brakes the same platform falls
    plant.reset(pose, equilibrium_tensions(reference8, pose))
    plant.set_commands(np.zeros(8))
    plant.advance(0.5)
    assert plant.pose.position[2] < pose.position[2] - 0.1


def test_disabled_drive_gives_way_and_pulls_again_when_enabled(suspended6: Robot) -> None:
    plant = Plant(suspended6)
    hold = plant.commands
    plant.set_drive_enabled(0, False)
    plant.advance(0.2)
    assert plant.forces[0] == 0.0
    assert plant.tensions[0] < 0.1 * -hold[0]
    plant.set_drive_enabled(0, True)
    plant.set_commands(hold - 50.0)  # reel in harder than holding
    plant.advance(0.5)
    assert plant.forces[0] < -50.0
    assert plant.tensions[0] > 20.0


def test_broken_cable_carries_nothing(reference8: Robot) -> None:
    plant = Plant(reference8)
    plant.break_cable(0)
    for _ in range(200):
        plant.step()
        assert plant.tensions[0] == 0.0
    assert deviation(reference8.home, plant.pose)[0] > 1e-3


def test_commands_are_saturated_and_checked(reference8: Robot) -> None:
    plant = Plant(reference8)
    plant.set_commands([1e4, -1e4, 0, 0, 0, 0, 0, 0])
    assert plant.commands[:2].tolist() == [600.0, -600.0]
    with pytest.raises(ValueError, match="expected 8 commands"):
        plant.set_commands([0.0] * 7)
    with pytest.raises(ValueError, match="command 3 is not finite"):
        plant.set_commands([0, 0, 0, math.nan, 0, 0, 0, 0])


def test_diverging_plant_raises(reference8: Robot) -> None:
    """Far beyond the stability limit (6-7 ms at EA = 1e5 N) the plant says so."""
    plant = Plant(reference8, config(step=1e-2))
    plant.reset(reference8.home, None, twist=0.1 * KICK)
    plant.set_brake(None, True)
    with pytest.raises(FloatingPointError, match="too long for the cable stiffness"):
        plant.advance(2.0)


# -- disturbance --------------------------------------------------------------------------


def test_step_disturbance_from_config_or_function(reference8: Robot) -> None:
    wrench = [30.0, 0.0, 0.0, 0.0, 0.0, 2.0]
    stepped = Plant(reference8, config(disturbance={"wrench": wrench, "start": 0.1}))
    function = Plant(reference8, disturbance=lambda t: wrench if t >= 0.1 else [0.0] * 6)
    for plant in (stepped, function):
        plant.set_brake(None, True)
    for i in range(300):
        stepped.step()
        function.step()
        if i < 100:
            assert deviation(reference8.home, stepped.pose)[0] < 1e-12
        np.testing.assert_array_equal(stepped.pose.position, function.pose.position)
    moved = liediff(reference8.home, stepped.pose)
    assert moved[0] > 1e-5 and moved[5] > 1e-5  # pushed along +x and turned about +z


# -- numerics and conventions -------------------------------------------------------------


def test_accurate_at_the_default_stiffness(reference8: Robot) -> None:
    """Default step against 20 substeps, for a disturbance smooth on the time scale of
    the cable modes (50 ms raised cosine): within 2 % of the response."""
    wrench = np.array([40.0, -30.0, 20.0, 3.0, -2.0, 4.0])

    def ramp(t: float) -> list[float]:
        s = min(t / 0.05, 1.0)
        return (wrench * (0.5 - 0.5 * math.cos(math.pi * s))).tolist()

    runs = []
    for substeps in (1, 20):
        plant = Plant(reference8, config(substeps=substeps), disturbance=ramp)
        plant.set_brake(None, True)
        motion = []
        for _ in range(500):
            plant.step()
            motion.append(liediff(reference8.home, plant.pose))
        runs.append(np.array(motion))
    coarse, fine = runs
    amplitude = np.abs(fine).max(axis=0)
    assert np.all(np.abs(coarse - fine).max(axis=0) < 0.02 * amplitude)


@pytest.fixture(scope="module", params=[("suspended6", 0.5), ("reference8", 0.2)], ids=str)
def swinging(request: pytest.FixtureRequest):
    """(robot, recording of every 0.1 ms step, h): the plant with stiff cables moving freely
    under constant commands after a kick (the crossed robot only briefly: it is unstable)."""
    name, seconds = request.param
    robot = load_robot(name)
    h = 1e-4
    stiff = {"stiffness": 1e7, "damping": 1e4}
    plant = Plant(robot, config(step=h, cable=stiff, encoder={"counts_per_metre": None}))
    pose = Pose.from_rotvec(robot.home.position + np.array([0.1, -0.05, 0.05]), [0.03, -0.02, 0.05])
    plant.reset(pose, equilibrium_tensions(robot, pose), twist=[0.2, -0.1, 0.15, 0.8, -0.6, 1.0])
    hold = plant.commands
    return robot, run_lockstep(plant, lambda *_: hold, seconds, 1 / h), h


SETTLE = 0.02  # s: the drum-cable vibration the kick excites, damped by then


def accelerations(rec, h: float) -> tuple[range, np.ndarray]:
    """Cycles after SETTLE (but the last) and α there by central differences."""
    phi = rec.twist
    cycles = range(round(SETTLE / h) + 1, len(rec) - 1)
    return cycles, np.array([(phi[i + 1] - phi[i - 1]) / (2 * h) for i in cycles])


def test_trajectory_satisfies_the_model_kinematics(swinging) -> None:
    """Along the plant's own motion, l' = Λ φ and l'' = Λ α + c (cdpr's Λ and c), for the
    geometric lengths and, the cables being stiff, for the drums."""
    robot, rec, h = swinging
    cycles, alpha = accelerations(rec, h)
    predicted, bias, rates = [], [], []
    for i, a in zip(cycles, alpha, strict=True):
        eta = rec.pose(i)
        c = robot.bias_accel(eta, rec.twist[i])
        predicted.append(robot.jacobian(eta) @ a + c)
        bias.append(c)
        rates.append(robot.jacobian(eta) @ rec.twist[i])
    predicted = np.array(predicted)
    scale = np.abs(predicted).max()
    assert np.abs(np.array(bias)).max() > 0.15 * scale  # c matters in this motion
    i = np.array(cycles)
    for lengths in (rec.cable_lengths, rec.lengths):
        second_difference = (lengths[i + 1] - 2 * lengths[i] + lengths[i - 1]) / h**2
        assert np.abs(second_difference - predicted).max() < 0.01 * scale
    rates = np.array(rates)
    assert np.abs(rec.rates[i] - rates).max() < 2e-3 * np.abs(rates).max()


def test_trajectory_satisfies_the_model_dynamics(swinging) -> None:
    """The same motion obeys cdpr's dynamics: the platform alone M_p α + μ_p = -Λᵀ t, and,
    the cables being stiff, the whole system M α + μ = Λᵀ f with the actuator forces f
    (the paper's τ = M α + μ with t = f0 - f)."""
    robot, rec, h = swinging
    cycles, alpha = accelerations(rec, h)
    platform, whole, platform_scale, whole_scale = [], [], [], []
    for i, a in zip(cycles, alpha, strict=True):
        eta, phi = rec.pose(i), rec.twist[i]
        Lam = robot.jacobian(eta)
        Mp = np.array(robot.platform.mass_and_bias(quat_to_r9(*eta.quaternion), phi)).reshape(6, 7)
        platform.append(Mp[:, :6] @ a + Mp[:, 6] + Lam.T @ rec.tensions[i])
        platform_scale.append(Mp[:, :6] @ a)
        M, mu = robot.dynamics(eta, phi)
        whole.append(M @ a + mu - Lam.T @ rec.forces[i])
        whole_scale.append(M @ a)
    for residual, scale in ((platform, platform_scale), (whole, whole_scale)):
        assert np.all(np.abs(residual).max(axis=0) < 0.01 * np.abs(scale).max(axis=0))


# -- sensors and determinism ------------------------------------------------------------


def test_encoder_quantisation_latency_and_velocity(reference8: Robot) -> None:
    cfg = config(encoder={"counts_per_metre": 1e4, "latency_steps": 3, "velocity_window_steps": 4})
    plant = Plant(reference8, cfg)
    plant.reset(reference8.home, None, twist=[0.1, 0.0, -0.05, 0.0, 0.0, 0.2])
    history = []
    for _ in range(20):
        plant.step()
        history.append(plant.drum_lengths)
    lengths, rates = plant.measure()
    counts = lengths * 1e4
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    np.testing.assert_allclose(lengths, history[-4], atol=0.5e-4 + 1e-12)
    older = np.round(history[-8] * 1e4) / 1e4
    np.testing.assert_allclose(rates, (lengths - older) / 4e-3, rtol=1e-9)


def test_encoder_noise_has_the_configured_std(reference8: Robot) -> None:
    plant = Plant(reference8, config(encoder={"counts_per_metre": None, "noise_std": 1e-4}))
    samples = np.array([plant.measure()[0] for _ in range(2000)]) - plant.drum_lengths
    assert abs(samples.std() / 1e-4 - 1.0) < 0.05
    assert abs(samples.mean()) < 1e-5


def test_runs_are_deterministic_given_the_seed(reference8: Robot) -> None:
    cfg = config(
        seed=7,
        encoder={"noise_std": 1e-5},
        mismatch={"anchor_error_std": 1e-3, "mass_scale": 1.05},
        friction={"coulomb": 2.0, "viscous": 1.0},
    )
    hold = -equilibrium_tensions(reference8, reference8.home)

    def controller(_t, lengths, rates):
        return hold - 1e4 * (lengths - home_lengths) - 200.0 * rates

    home_lengths = reference8.cable_lengths(reference8.home)
    runs = [run_lockstep(Plant(reference8, c), controller, 0.5, 500) for c in (cfg, cfg)]
    for name in runs[0].series:
        np.testing.assert_array_equal(runs[0][name], runs[1][name])
    other = run_lockstep(
        Plant(reference8, cfg.model_copy(update={"seed": 8})), controller, 0.5, 500
    )
    assert np.abs(other.measured_lengths - runs[0].measured_lengths).max() > 0.0
