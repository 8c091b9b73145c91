"""The parallel-actuator controller closed-loop on the simulated robot (lock-step).

Each run is a few seconds of simulated time at 500 Hz; figures are of the TRUE platform
(the plant) against the reference."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import ConfigError, Pose, Robot, liediff, retract
from cdpr.baseline import JointSpaceController
from cdpr.control_spec import ControllerSpec, parse_controller
from cdpr.controller import Hold, ParallelController
from cdpr.measurement import ERROR, ERROR_RATE
from cdpr.trajectory import Reference, Trajectory, TrajectoryLimits, goto
from sim_bus.plant import Plant, equilibrium_tensions
from sim_bus.plant.config import parse_plant_config
from tests.closed_loop import RATE, hold_run, pose_errors
from tuning.lockstep import run_lockstep
from tuning.scenarios import STANDARD_SET
from tuning.tracking import run_tracking


@pytest.mark.parametrize("model_at", ["reference", "measured"])
def test_holds_home_still(reference8: Robot, model_at: str) -> None:
    controller = ParallelController(reference8, parse_controller({"model_at": model_at}))
    rec, outputs = hold_run(reference8, controller, reference8.home, 3.0)
    pos, ang = pose_errors(rec, reference8.home)
    assert all(o.feasible for o in outputs)
    assert pos.max() < 1e-4 and np.degrees(ang.max()) < 0.01
    assert rec.tensions.min() > reference8.t_min.min() * 0.5


class LiteralStep5(ParallelController):
    """The paper's step 5 read literally: theta_d = liediff(eta, eta_r) ~ eta_r - eta,
    and its rate phi_r - phi: exactly the negated error the controller measures
    (liediff(a, b) = -liediff(b, a), test_the_literal_reading_is_the_negated_error), so
    the measurement's error is negated before the loop sees it."""

    def _measure(self, *args):
        fk, measured = super()._measure(*args)
        if measured is not None:
            measured[ERROR] *= -1.0
            measured[ERROR_RATE] *= -1.0
        return fk, measured


def test_the_literal_reading_is_the_negated_error() -> None:
    a = Pose.from_rotvec((0.1, -0.2, 1.3), (0.3, -0.2, 0.5))
    b = Pose.from_rotvec((0.12, -0.25, 1.31), (0.28, -0.1, 0.45))
    assert np.allclose(liediff(b, a), -liediff(a, b), rtol=0.0, atol=1e-15)


@pytest.mark.parametrize("model_at", ["reference", "measured"])
def test_sign_erratum_ours_converges_the_literal_reading_diverges(
    reference8: Robot, model_at: str
) -> None:
    """DESIGN §3: from a 5 mm / 0.5 deg offset, theta_d = liediff(eta_r, eta) settles
    (to 0.1 mm in 4.5 s: the integral action's tail);
    the literal liediff(eta, eta_r) turns the PID into positive feedback and runs away."""
    target = Pose.from_rotvec(
        reference8.home.position + np.array((0.003, -0.002, 0.003)), np.radians((0.3, -0.2, 0.3))
    )
    spec = parse_controller({"model_at": model_at})
    rec, outputs = hold_run(reference8, ParallelController(reference8, spec), target, 4.5)
    pos, ang = pose_errors(rec, target)
    assert all(o.feasible for o in outputs)
    assert pos[-100:].max() < 1e-4 and ang[-100:].max() < np.radians(0.05)

    rec, outputs = hold_run(reference8, LiteralStep5(reference8, spec), target, 2.0)
    pos, _ = pose_errors(rec, target)
    ran_away = pos.max() > 0.05 or not all(o.feasible for o in outputs)
    assert ran_away and pos.max() > 10 * 0.0047


@pytest.mark.parametrize("model_at", ["reference", "measured"])
@pytest.mark.parametrize("scenario", sorted(STANDARD_SET))
def test_standard_set_tracks_within_a_millimetre(scenario: str, model_at: str) -> None:
    robot = Robot.from_yaml("config/robots/reference8.yaml")
    trajectory = STANDARD_SET[scenario](robot)
    controller = ParallelController(robot, parse_controller({"model_at": model_at}))
    result = run_tracking(robot, trajectory, controller, rate_hz=RATE)
    assert result.fault == ""
    assert result.rms_mm <= 1.0, result.figures()
    assert result.slack_events == 0 and result.min_tension > 10.0


@pytest.mark.parametrize("scenario", sorted(STANDARD_SET))
def test_model_mismatch_stays_stable_and_bounded(scenario: str) -> None:
    """Plant mass +10 %, m0 -10 %, encoder quantisation and 5 um noise."""
    robot = Robot.from_yaml("config/robots/reference8.yaml")
    plant = parse_plant_config(
        {
            "mismatch": {"mass_scale": 1.1, "m0_scale": 0.9},
            "encoder": {"counts_per_metre": 1e5, "noise_std": 5e-6},
            "seed": 7,
        }
    )
    trajectory = STANDARD_SET[scenario](robot)
    result = run_tracking(robot, trajectory, ParallelController(robot), plant, RATE)
    assert result.fault == ""
    assert result.max_mm < 8.0 and result.max_deg < 1.0, result.figures()
    assert result.slack_events == 0


def test_baseline_tracks_the_standard_set(reference8: Robot) -> None:
    """The joint-space baseline is a working controller (so the comparison is fair)."""
    trajectory = STANDARD_SET["vertical_lift"](reference8)
    result = run_tracking(reference8, trajectory, JointSpaceController(reference8))
    assert result.fault == "" and result.rms_mm < 3.0


def test_pose_outside_the_wrench_set_is_infeasible(reference8: Robot) -> None:
    controller = ParallelController(reference8)
    lengths = reference8.drum_lengths(
        reference8.cable_lengths(reference8.home), controller._tensions
    )
    assert controller.step(0.0, lengths, np.zeros(8)).feasible
    tilted = Pose.from_rotvec(reference8.home.position, (0.0, np.radians(60.0), 0.0))
    controller.follow(Hold(tilted))
    out = controller.step(0.002, lengths, np.zeros(8))
    assert not out.feasible and out.reason.startswith("wrench not in W")
    assert np.all(np.isnan(out.commands))


def test_bad_measurements_are_reported_not_raised(reference8: Robot) -> None:
    controller = ParallelController(reference8)
    lengths = reference8.drum_lengths(
        reference8.cable_lengths(reference8.home), controller._tensions
    )
    bad = lengths.copy()
    bad[3] = np.nan
    out = controller.step(0.0, bad, np.zeros(8))
    assert not out.feasible and "forward kinematics" in out.reason and "cable 3" in out.reason
    rates = np.zeros(8)
    rates[1] = np.inf
    out = controller.step(0.0, lengths, rates)
    assert not out.feasible and "twist" in out.reason
    inconsistent = lengths.copy()
    inconsistent[5] += 0.03  # no pose has these lengths
    out = controller.step(0.0, inconsistent, np.zeros(8))
    assert not out.feasible and "residual" in out.reason


def test_outputs_satisfy_the_papers_relations(reference8: Robot) -> None:
    """Step 7-11 identities on one cycle: Lambda^T f_p = tau_c, t = f0 - f_p, f_c = f_p + f_b,
    with the model and f_b for the command's instant, t + lead (the measured pose carried
    there by its twist, the reference sampled there)."""
    spec = ControllerSpec(model_at="measured")
    controller = ParallelController(reference8, spec)
    trajectory = STANDARD_SET["figure_eight"](reference8)
    ref = trajectory.sample(2.0)
    controller.reset(ref.pose)
    controller.follow(trajectory)
    lengths = reference8.drum_lengths(reference8.cable_lengths(ref.pose), controller._tensions)
    rates = reference8.jacobian(ref.pose) @ ref.twist
    out = controller.step(2.0, lengths, rates)
    assert out.feasible and controller.lead > 0.0
    Lam = reference8.jacobian(retract(out.pose, out.twist * controller.lead))
    np.testing.assert_allclose(Lam.T @ out.f_p, out.tau_c, atol=1e-5)
    np.testing.assert_allclose(out.tensions, out.f0 - out.f_p, atol=1e-9)
    np.testing.assert_allclose(out.commands, out.f_p + out.f_b, atol=1e-12)
    ahead = trajectory.sample(2.0 + controller.lead)
    np.testing.assert_allclose(
        out.f_b, reference8.k0 * (reference8.jacobian(ahead.pose) @ ahead.twist)
    )
    assert np.all(out.tensions >= reference8.t_min - 1e-6)


@pytest.mark.parametrize("model_at", ["reference", "measured"])
def test_prepared_steps_equal_plain_steps(reference8: Robot, model_at: str) -> None:
    """prepare(t) ahead of step(t, ...) changes nothing but when the work is done."""
    spec = ControllerSpec(model_at=model_at)
    trajectory = STANDARD_SET["figure_eight"](reference8)
    run = run_tracking(reference8, trajectory, ParallelController(reference8, spec))
    rec = run.recording
    plain, ahead = ParallelController(reference8, spec), ParallelController(reference8, spec)
    for controller in (plain, ahead):
        controller.reset(rec.pose(0))
        controller.follow(trajectory)
    for k in range(min(len(rec), 600)):  # every cycle: the controllers carry state
        t = float(rec.t[k])
        ahead.prepare(t)
        a = plain.step(t, rec.measured_lengths[k], rec.measured_rates[k])
        b = ahead.step(t, rec.measured_lengths[k], rec.measured_rates[k])
        assert a.feasible and b.feasible
        np.testing.assert_array_equal(a.commands, b.commands)
        np.testing.assert_array_equal(a.tensions, b.tensions)
        assert a.pose == b.pose


@pytest.mark.parametrize("model_at", ["reference", "measured"])
@pytest.mark.parametrize("source", ["hold", "goto"])
def test_a_reference_at_rest_reuses_its_terms_bit_for_bit(
    reference8: Robot, model_at: str, source: str
) -> None:
    """The reference terms (f_b, the model at the reference, the tension distribution's
    factor) of a reference at rest, the same Reference sample after sample (a Hold, a
    goto past its end), are evaluated once and reused while the platform model stands:
    every output equals that of terms evaluated afresh each cycle, through a payload
    estimate that moves the model, a payload set by hand and a new source."""
    spec = parse_controller({"model_at": model_at})
    target = Pose.from_rotvec(
        reference8.home.position + np.array((0.003, -0.002, 0.003)), np.radians((0.3, -0.2, 0.3))
    )
    rec, _ = hold_run(reference8, ParallelController(reference8, spec), target, 1.5)

    def make() -> Hold | Trajectory:
        if source == "hold":
            return Hold(target)
        rest = Reference(rec.pose(0), np.zeros(6), np.zeros(6))
        return goto(rest, target, TrajectoryLimits())  # over within the first half

    cached, fresh = ParallelController(reference8, spec), ParallelController(reference8, spec)
    first = make()
    for controller in (cached, fresh):
        controller.reset(rec.pose(0))
        controller.follow(first)
    platforms = set()
    for k in range(len(rec)):
        t = float(rec.t[k])
        if k == len(rec) // 2:
            again = make()
            for controller in (cached, fresh):
                controller.set_payload(controller.robot.platform.mass * 1.05, (0.0, 0.0, 0.0))
                controller.follow(again)
        fresh._terms = None  # evaluated afresh, as before they were kept
        for controller in (cached, fresh):
            controller.prepare(t)
        a = cached.step(t, rec.measured_lengths[k], rec.measured_rates[k])
        b = fresh.step(t, rec.measured_lengths[k], rec.measured_rates[k])
        assert a.feasible and b.feasible
        for name in ("commands", "tensions", "f_b", "tau_c", "f0", "alpha_c"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert a.pose == b.pose
        platforms.add(id(cached.robot.platform))
    assert len(platforms) > 2  # the estimate moved the model, and so did set_payload


def test_a_preparation_is_dropped_by_follow_and_by_another_time(reference8: Robot) -> None:
    controller = ParallelController(reference8)
    lengths = reference8.drum_lengths(
        reference8.cable_lengths(reference8.home), controller._tensions
    )
    trajectory = STANDARD_SET["vertical_lift"](reference8)
    controller.follow(trajectory)
    controller.prepare(0.5)
    out = controller.step(1.0, lengths, np.zeros(8))  # not the prepared time
    assert out.reference.pose == trajectory.sample(1.0).pose
    controller.prepare(1.002)
    moved = Pose.from_rotvec(reference8.home.position + np.array([0.0, 0.0, 0.01]), np.zeros(3))
    controller.follow(Hold(moved))  # a new source after the preparation
    out = controller.step(1.002, lengths, np.zeros(8))
    assert out.reference.pose == moved


def test_a_source_followed_from_a_time_takes_over_then(reference8: Robot) -> None:
    """follow(source, at): the current reference until `at`, the new one from then; a
    later follow drops the switches already past."""
    controller = ParallelController(reference8)
    lengths = reference8.drum_lengths(
        reference8.cable_lengths(reference8.home), controller._tensions
    )
    first = controller.source
    lift = STANDARD_SET["vertical_lift"](reference8)
    controller.follow(lift, at=0.5)
    assert controller.source.sample(0.499).pose == first.sample(0.499).pose
    assert controller.source.sample(0.5).pose == lift.sample(0.5).pose
    out = controller.step(0.4, lengths, np.zeros(8))
    assert out.reference.pose == reference8.home  # still the hold before the switch
    moved = Hold(
        Pose(reference8.home.position + np.array([0.0, 0.0, 0.01]), np.array([1.0, 0, 0, 0]))
    )
    controller.follow(moved, at=0.6)  # the switch at 0.5 is still ahead: kept
    assert controller.source.before.before is first
    controller.step(0.55, lengths, np.zeros(8))
    controller.follow(Hold(reference8.home), at=0.7)  # the switch at 0.5 is past: dropped
    assert controller.source.before.before is lift


# -- command timing ---------------------------------------------------------

GOAL_MM = {"figure_eight": 0.10, "vertical_lift": 0.08, "edge_move": 0.15}


@pytest.mark.slow  # over 4.5 s
@pytest.mark.parametrize("scenario", sorted(STANDARD_SET))
def test_the_command_lead_cuts_the_tracking_error(reference8: Robot, scenario: str) -> None:
    """Evaluated for the middle of the interval it acts over (auto: half a period plus
    the drive's 2 ms lag; lock-step applies commands at once), each command tracks the
    standard set at least three times better than evaluated for its measurement's
    instant (measured: 5-8 times), and within the goals.  The external wrench
    observer is off: it takes part of a late command's error too (edge move without the
    lead: 0.13 mm with it, 0.49 mm without)."""
    trajectory = STANDARD_SET[scenario](reference8)
    rms = {}
    off = {"enabled": False}
    for lead in ("auto", 0.0):
        spec = ControllerSpec.model_validate({"command_lead": lead, "disturbance_observer": off})
        controller = ParallelController(reference8, spec)
        result = run_tracking(reference8, trajectory, controller, rate_hz=RATE)
        assert result.fault == "" and result.slack_events == 0
        rms[lead] = result.rms_mm
    assert rms["auto"] <= rms[0.0] / 3.0, rms
    assert rms["auto"] <= GOAL_MM[scenario], rms


def test_the_twist_estimate_does_not_lag_under_acceleration(reference8: Robot) -> None:
    """With a cable stiffness the drives' rates are corrected from the poses' differences
    (a complementary filter).  The difference over a period is the mean twist over it:
    held against this cycle's drive twist alone, the estimate settled half a period
    behind (-alpha T/2: 2 mm/s here); the drives' exact rates must come out unbiased.
    (The platform runs away from the held pose: the payload estimate and the external
    wrench observer, off here, would take the growing feedback wrench for a payload or
    a push beyond their limits.)"""
    assert np.any(reference8.compliance > 0.0)  # the stretch-correcting estimate
    spec = ControllerSpec(adaptation={"enabled": False}, disturbance_observer={"enabled": False})
    controller = ParallelController(reference8, spec)
    accel = np.array([2.0, -1.0, 1.5])  # m/s^2, pure translation from rest
    period = controller.period
    errors = []
    for k in range(250):  # 0.5 s: ten filter time constants
        t = k * period
        pose = Pose(reference8.home.position + 0.5 * accel * t**2, reference8.home.quaternion)
        twist = np.concatenate([accel * t, np.zeros(3)])
        # the drums' lengths under the tensions the controller planned: the poses exact
        lengths = reference8.drum_lengths(reference8.cable_lengths(pose), controller._tensions)
        out = controller.step(t, lengths, reference8.jacobian(pose) @ twist)
        errors.append(out.twist - twist)
    bias = np.abs(np.array(errors[-25:])).max(axis=0)
    assert bias[:3].max() < 0.1 * np.linalg.norm(accel) * period / 2, bias
    assert bias[3:].max() < 1e-4, bias


@pytest.mark.parametrize(
    "value", [-0.001, 0.5, float("inf"), float("nan"), "soon", True, None, [0.003]]
)
def test_command_lead_config_refuses_bad_values_by_name(value: object) -> None:
    with pytest.raises(ConfigError) as info:
        parse_controller({"command_lead": value}, "robot.yaml")
    message = str(info.value)
    assert message.startswith("robot.yaml: controller.command_lead: must be")
    assert '"auto" or a time in seconds from 0 to 0.1' in message


def test_command_lead_auto_allows_for_latency_lag_and_half_a_period(reference8: Robot) -> None:
    auto = ParallelController(reference8, parse_controller({"rate_hz": 1000.0}), drive_lag=0.003)
    assert auto.lead == pytest.approx(0.0005 + 0.003)
    auto.set_latency(0.0002)
    assert auto.lead == pytest.approx(0.0002 + 0.0005 + 0.003)
    fixed = ParallelController(reference8, parse_controller({"command_lead": 0.004}))
    fixed.set_latency(0.0002)
    assert fixed.lead == 0.004
    with pytest.raises(ValueError, match="latency must be finite and >= 0 s"):
        auto.set_latency(-1e-4)


class HeldAt(ParallelController):
    """Holds its external wrench observer out of the loop from time `at` on."""

    at = 2.0

    def step(self, t, lengths, length_rates):
        if t >= self.at and not self.observer_held:
            self.hold_observer(True)
        return super().step(t, lengths, length_rates)


def test_holding_the_observer_hands_its_estimate_to_the_integral_action(
    reference8: Robot,
) -> None:
    """A 20 N push taken in by the observer; held, its estimate leaves the command and
    the integral action takes it on in the same cycle: the commands do not step (the
    push spread over the cables, several N each, if nothing took it on), the platform
    stays put, and the estimate stays zero while held.  Ideal encoders: the counts'
    quantisation moves the commands by up to ~1 N from cycle to cycle in bursts, which
    would decide whether the cycle of the hand-over looked still."""
    plant = parse_plant_config({
        "disturbance": {"wrench": [20.0, 0.0, 0.0, 0.0, 0.0, 0.0]},
        "encoder": {"counts_per_metre": None},
    })  # fmt: skip
    controller = HeldAt(reference8)
    rec, outputs = hold_run(reference8, controller, reference8.home, 3.0, plant_config=plant)
    assert all(o.feasible for o in outputs)
    k = int(np.searchsorted(rec.t, HeldAt.at))
    before, held = outputs[k - 1].commands, outputs[k].commands
    assert np.abs(held - before).max() < 0.05  # 4.6 N without the integral taking it on
    assert controller.observer.estimate.tolist() == [0.0] * 6
    pos, _ = pose_errors(rec, reference8.home)
    assert pos[k:].max() < pos[k - 1] + 1e-5  # 8 mm further without


def _tracking_pair(robot: Robot, spec: ControllerSpec, cycles: int):
    """Two controllers with the same history of `cycles` steps of the figure eight, and
    the recording to continue it from."""
    trajectory = STANDARD_SET["figure_eight"](robot)
    rec = run_tracking(robot, trajectory, ParallelController(robot, spec)).recording
    pair = ParallelController(robot, spec), ParallelController(robot, spec)
    for controller in pair:
        controller.reset(rec.pose(0))
        controller.follow(trajectory)
        for k in range(cycles):
            controller.step(float(rec.t[k]), rec.measured_lengths[k], rec.measured_rates[k])
    return pair, rec


INVALIDATING = {
    "reset": lambda c, t: c.reset(retract(c.pose, np.r_[0.002, 0.0, 0.0, 0.0, 0.01, 0.0])),
    "follow": lambda c, t: c.follow(Hold(c.pose)),
    "set_latency": lambda c, t: c.set_latency(0.004),
    "set_payload": lambda c, t: c.set_payload(c.robot.platform.mass * 1.1, (0.0, 0.0, 0.0)),
}


@pytest.mark.parametrize("action", [*INVALIDATING, "another time"])
def test_a_preparation_is_not_used_after_what_changes_it(reference8: Robot, action: str) -> None:
    """A cycle prepared (reference, model, forward kinematics' linearisation at the guess,
    the tension distribution's factor) and then reset, given a new source, a new latency
    or payload, or stepped at another time, steps as if prepared again after that."""
    (stale, fresh), rec = _tracking_pair(reference8, ControllerSpec(), 200)
    t = float(rec.t[200])
    for controller in (stale, fresh):
        if action == "another time":
            controller.prepare(float(rec.t[199]))  # a cycle that was not stepped
        else:
            controller.prepare(t)
            INVALIDATING[action](controller, t)
    fresh.prepare(t)
    a = stale.step(t, rec.measured_lengths[200], rec.measured_rates[200])
    b = fresh.step(t, rec.measured_lengths[200], rec.measured_rates[200])
    assert a.feasible and b.feasible
    np.testing.assert_array_equal(a.commands, b.commands)
    np.testing.assert_array_equal(a.tensions, b.tensions)
    assert a.pose == b.pose


def _stalled_goto(robot: Robot, stalls: list[tuple[int, int]]) -> tuple[float, float]:
    """A 0.25 m goto, lock-step at 500 Hz, with the host held up over the cycles
    [a, b) of each stall (the drives keep the last command; no step runs): the largest
    external force the observer estimated (N) and the platform's largest distance from
    the reference (mm)."""
    home = robot.home
    rest = Reference(home, np.zeros(6), np.zeros(6))
    target = Pose(home.position + np.array([0.25, 0.0, 0.0]), home.quaternion)
    trajectory = goto(rest, target, TrajectoryLimits())
    plant = Plant(robot)
    plant.reset(home, equilibrium_tensions(robot, home))
    controller = ParallelController(robot)
    controller.reset(home)
    controller.follow(trajectory)
    observer = controller.observer
    assert observer is not None
    last: list[np.ndarray] = []
    pushes: list[float] = []

    def control(t: float, lengths: np.ndarray, rates: np.ndarray) -> np.ndarray:
        k = round(t * RATE)
        if last and any(a <= k < b for a, b in stalls):
            return last[-1]
        out = controller.step(t, lengths, rates)
        last.append(out.commands)
        pushes.append(float(np.linalg.norm(observer.estimate[:3])))
        return out.commands

    rec = run_lockstep(plant, control, 1.2, RATE)
    errors = [liediff(trajectory.sample(t).pose, rec.pose(i))[:3] for i, t in enumerate(rec.t)]
    return max(pushes), float(np.linalg.norm(errors, axis=1).max() * 1e3)


def test_a_host_held_up_mid_motion_is_not_taken_for_a_push(reference8: Robot) -> None:
    """A host held up for 10 ms (five cycles) now and then during a goto: the drives
    latched their positions that much apart, and the controller takes the gap as it
    is.  Differenced over a period instead, it made the observer see a 25 N push and
    the platform left the reference by 18 mm (main at 006acb2; the daemon braked on
    tracking_error in tests on a slower host)."""
    calm_push, calm_error = _stalled_goto(reference8, [])
    stalls = [(s, s + 5) for s in range(40, 300, 37)]
    push, error = _stalled_goto(reference8, stalls)
    assert push < calm_push + 2.0, (push, calm_push)
    assert error < calm_error + 1.0, (error, calm_error)
