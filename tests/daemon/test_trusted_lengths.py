"""daemon.service.trusted_lengths: which measured cable lengths the brake may hold (DESIGN §9).

A forged or glitching length must never become a hold target: it fails the rate, step
or consistency check, names its drive, and the cable keeps its last trusted length."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot
from cdpr.trajectory.limits import TrajectoryLimits
from daemon.service.trusted_lengths import (
    RETRY,
    Implausible,
    TrustedLengths,
    cable_accel_bound,
)

ROBOT = Robot.from_yaml(Path(__file__).resolve().parents[2] / "config/robots/reference8.yaml")
NODES = [11, 12, 13, 14, 15, 16, 17, 18]
PERIOD = 0.002
SPEED = 3.0
TOLERANCE = 1e-3
SLACK = 2 * PERIOD + 0.01
STILL = [0.0] * 8
FRESH = [True] * 8


def make(max_accel: float = 0.0) -> TrustedLengths:
    return TrustedLengths(
        ROBOT,
        NODES,
        max_speed=SPEED,
        tolerance=TOLERANCE,
        slack=SLACK,
        rest_tensions=[0.0] * 8,
        max_accel=max_accel,
    )


def lengths_at(dx: float = 0.0, dy: float = 0.0, dz: float = 0.0, rz: float = 0.0) -> list[float]:
    home = ROBOT.home
    pose = Pose.from_rotvec(home.position + np.array([dx, dy, dz]), [0.0, 0.0, rz])
    return ROBOT.cable_lengths(pose).tolist()


def rates_between(before: list[float], after: list[float], dt: float) -> list[float]:
    return [(b - a) / dt for a, b in zip(before, after, strict=True)]


def named(problem: Implausible) -> set[int]:
    """The cables a fault names: its own, and those 'disagreeing as much'."""
    return {problem.cable} | {int(k) for k in re.findall(r"(\d+) \(node", problem.reason)}


def moving(
    velocity: tuple[float, float, float, float], cycles: int = 2, follow: str | None = None
):
    """A trust that saw the platform leave home at `velocity` ((vx, vy, vz) m/s, wz rad/s)
    for `cycles` cycles, rates reported, with `follow`: the measured pose passed to
    follow_pose every cycle ("at_once"), or to note_pose with catch_up before the next
    check (as the service does: "next_tick").  (trust, where it is, its instant)."""
    trust = trusted_at_home()
    at = [0.0] * 4
    for cycle in range(1, cycles + 1):
        before, at = lengths_at(*at), [a + v * PERIOD for a, v in zip(at, velocity, strict=True)]
        now = lengths_at(*at)
        trust.catch_up()
        assert trust.check(now, rates_between(before, now, PERIOD), FRESH, cycle * PERIOD) == []
        pose = Pose.from_rotvec(ROBOT.home.position + np.array(at[:3]), [0, 0, at[3]])
        if follow == "at_once":
            trust.follow_pose(pose)
        elif follow == "next_tick":
            trust.note_pose(pose)
    trust.catch_up()
    return trust, at, cycles * PERIOD


def step_on(at: list[float], velocity: tuple[float, ...], dt: float = PERIOD):
    """The next sample: (lengths, rates, where)."""
    before, after = lengths_at(*at), [a + v * dt for a, v in zip(at, velocity, strict=True)]
    now = lengths_at(*after)
    return now, rates_between(before, now, dt), after


def trusted_at_home() -> TrustedLengths:
    trust = make()
    assert trust.check(lengths_at(), STILL, FRESH, 0.0) == []
    assert trust.held == lengths_at()
    return trust


def test_the_first_complete_set_is_trusted_when_it_fits_one_pose() -> None:
    trust = make()
    partial = [True] * 7 + [False]
    assert trust.check(lengths_at(), STILL, partial, 0.0) == []  # not complete: waits
    assert all(math.isnan(x) for x in trust.held)
    assert trust.check(lengths_at(), STILL, FRESH, PERIOD) == []
    assert trust.held == lengths_at()


def test_a_first_set_that_fits_no_pose_is_not_trusted_and_names_the_drive() -> None:
    trust = make()
    forged = lengths_at()
    forged[0] = 4.1  # really 2.33 m
    [problem] = trust.check(forged, STILL, FRESH, 0.0)
    # without history only the geometry can tell, and at this symmetric pose it cannot
    # tell cable 0 from three others: all four are named
    assert 0 in named(problem) and "(node 11)" in problem.message()
    assert "the lengths fit no pose" in problem.message()
    assert all(math.isnan(x) for x in trust.held)
    # retried at most every RETRY seconds: the failure stands meanwhile
    assert trust.check(lengths_at(), STILL, FRESH, RETRY / 2) == [problem]
    assert trust.check(lengths_at(), STILL, FRESH, RETRY) == []
    assert trust.held == lengths_at()


def test_a_jump_beyond_the_step_bound_keeps_the_last_trusted_length() -> None:
    trust = trusted_at_home()
    forged = lengths_at()
    forged[0] = 4.1
    [problem] = trust.check(forged, STILL, FRESH, PERIOD)
    bound = SPEED * (PERIOD + SLACK) + TOLERANCE
    assert problem.cable == 0 and problem.value == 4.1
    assert problem.message() == (
        f"drive 0 (node 11): length 4.1000 m is {4.1 - lengths_at()[0]:+.4f} m from its "
        f"trusted {lengths_at()[0]:.4f} m after 2.0 ms (bound {bound:.4f} m at "
        "max_cable_speed 3 m/s)"
    )
    assert trust.held == lengths_at()  # cable 0 kept its trusted length, the others theirs
    # the forgery goes on: it stays implausible, and the hold target never moves
    for cycle in range(2, 200):
        faults = trust.check(forged, STILL, FRESH, cycle * PERIOD)
        assert [f.cable for f in faults] == [0]
        assert trust.held == lengths_at()


def test_two_answers_to_one_sync_that_disagree_name_the_odd_one_whichever_came_first() -> None:
    """A late answer to the SYNC before differs by at most the motion over `slack`: not
    implausible.  More apart, the length farther from the trusted one is named (the
    forged 4.1 m, not the true 2.33 m), with the other and the bound."""
    trust = trusted_at_home()
    true = lengths_at()[0]
    bound = SPEED * SLACK + TOLERANCE
    assert trust.second_answer(0, true, true + 0.99 * bound) is None  # a late answer
    assert trust.second_answer(0, true, true - 0.99 * bound) is None
    for first, second in [(true, 4.1), (4.1, true)]:
        problem = trust.second_answer(0, first, second)
        assert problem is not None and (problem.cable, problem.value) == (0, 4.1)
        assert problem.message() == (
            f"drive 0 (node 11): length 4.1000 m and {true:.4f} m in two answers to one "
            f"SYNC, {4.1 - true:.4f} m apart (bound {bound:.4f} m at max_cable_speed 3 m/s):"
            " a second answer to one SYNC means another node sends this node's PDOs "
            "(node-id conflict or forgery)"
        )
    far = trust.second_answer(0, true, true + 1.01 * bound)
    assert far is not None and far.value == true + 1.01 * bound
    assert trust.held == lengths_at()  # judging a pair trusts nothing
    # nothing trusted yet: the second answer is named
    assert make().second_answer(2, 4.1, 2.0).message().startswith("drive 2 (node 13): length 2.0")


def test_the_others_move_on_while_one_cable_is_rejected_for_its_step() -> None:
    trust = trusted_at_home()
    moved = lengths_at(dz=1e-3)
    sample = list(moved)
    sample[4] += 0.5
    rates = rates_between(lengths_at(), moved, PERIOD)
    assert [f.cable for f in trust.check(sample, rates, FRESH, PERIOD)] == [4]
    expected = list(moved)
    expected[4] = lengths_at()[4]
    assert trust.held == pytest.approx(expected, abs=1e-12)


def test_the_step_bound_grows_with_the_time_since_the_trusted_sample() -> None:
    trust = trusted_at_home()
    far = lengths_at(dx=0.05)  # 5 cm in 40 ms from rest, within max_cable_speed
    accelerating = [2 * r for r in rates_between(lengths_at(), far, 0.04)]
    assert trust.check(far, accelerating, FRESH, 0.04) == []
    assert trust.held == far


def test_a_rate_above_max_cable_speed_is_implausible() -> None:
    trust = trusted_at_home()
    rates = [0.0] * 8
    rates[6] = -3.5
    [problem] = trust.check(lengths_at(), rates, FRESH, PERIOD)
    assert problem.cable == 6 and problem.node == 17 and problem.value == -3.5
    assert problem.reason == "rate -3.5000 m/s exceeds max_cable_speed 3 m/s"


def test_a_cable_standing_still_that_jumps_is_named_by_its_own_rate() -> None:
    trust = trusted_at_home()
    sample = lengths_at()
    sample[3] += 5e-3  # within the step bound (49 mm), but its drive reports rate 0
    [problem] = trust.check(sample, STILL, FRESH, PERIOD)
    assert problem.cable == 3 and problem.node == 14
    assert problem.reason == (
        f"length {sample[3]:.4f} m moved +5.00 mm in 2.0 ms where its rate gives +0.00 mm "
        "(allowed 1.00 mm)"
    )
    assert trust.held == lengths_at()


def test_one_cable_disagreeing_with_the_pose_of_the_others_is_named() -> None:
    velocity = (0.5, 0.0, 0.0, 0.0)
    trust, at, t = moving(velocity)
    before = list(trust.held)
    sample, rates, at = step_on(at, velocity)
    sample[1] += 3e-3  # within what its rate allows at 0.5 m/s, not what the others say
    [problem] = trust.check(sample, rates, FRESH, t + PERIOD)
    assert 1 in named(problem)
    assert "with the pose the other cables give (feedback_tolerance 1.00 mm)" in problem.reason
    assert trust.held == before  # nothing of an inconsistent set is trusted
    # the glitch is over: the next sample agrees and is trusted
    sample, rates, at = step_on(at, velocity)
    assert trust.check(sample, rates, FRESH, t + 2 * PERIOD) == []
    assert trust.held == sample


def test_cables_the_geometry_cannot_tell_apart_are_all_named() -> None:
    """At reference8's symmetric home pose the null-space rows of cables 0, 3, 4 and 7
    are parallel: an error on any of them looks the same to the consistency check."""
    velocity = (0.0, 0.0, 0.5, 0.0)
    trust, at, t = moving(velocity, cycles=1)
    sample, rates, _ = step_on(at, velocity)
    sample[0] += 3e-3
    [problem] = trust.check(sample, rates, FRESH, t + PERIOD)
    assert named(problem) == {0, 3, 4, 7}
    assert "the geometry cannot tell them apart" in problem.reason


@settings(max_examples=60, deadline=None)
@given(
    cable=st.integers(0, 7),
    offset=st.floats(4 * TOLERANCE, 0.04) | st.floats(-0.04, -4 * TOLERANCE),
    velocity=st.tuples(*[st.floats(-0.5, 0.5)] * 4),
)
def test_the_outlier_is_found_whatever_the_motion(
    cable: int, offset: float, velocity: tuple[float, float, float, float]
) -> None:
    """Moving at up to 0.5 m/s (or rad/s) with rates that say so, one cable off by 4 mm
    to 40 mm is never trusted and always among the drives named."""
    trust, at, t = moving(velocity)
    before = list(trust.held)
    sample, rates, _ = step_on(at, velocity)
    sample[cable] += offset
    faults = trust.check(sample, rates, FRESH, t + PERIOD)
    assert cable in set().union(*map(named, faults))
    assert trust.held[cable] == before[cable]


@settings(max_examples=40, deadline=None)
@given(velocity=st.tuples(*[st.floats(-1.0, 1.0)] * 4))
def test_rigid_motion_within_the_speed_is_trusted(velocity: tuple[float, ...]) -> None:
    trust, at, t = moving(velocity)
    sample, rates, _ = step_on(at, velocity)
    assert trust.check(sample, rates, FRESH, t + PERIOD) == []
    assert trust.held == sample


def test_a_cycle_without_every_sample_trusts_nothing() -> None:
    trust = trusted_at_home()
    partial = [True] * 8
    partial[2] = False
    sample = lengths_at(dy=1e-3)
    rates = rates_between(lengths_at(), sample, PERIOD)
    assert trust.check(sample, rates, partial, PERIOD) == []
    assert trust.held == lengths_at()
    nan = list(sample)
    nan[5] = math.nan  # the NaN trigger reports it; it is simply not trusted
    assert trust.check(nan, rates, FRESH, 2 * PERIOD) == []
    assert trust.held == lengths_at()


def test_a_stale_sample_already_trusted_is_not_judged_again() -> None:
    """After a 50 ms stall a moving cable's old sample (no newer one came) does not
    disagree with its own rate: it is the trusted sample itself."""
    velocity = (0.5, 0.0, 0.0, 0.0)
    trust, at, t = moving(velocity)
    stale = [True] * 8
    stale[0] = False
    previous = [a - v * PERIOD for a, v in zip(at, velocity, strict=True)]
    _, last_rates, _ = step_on(previous, velocity)
    sample, rates, _ = step_on(at, velocity, dt=0.05)
    sample[0], rates[0] = lengths_at(*at)[0], last_rates[0]  # cable 0's last sample
    assert trust.check(sample, rates, stale, t + 0.05) == []


def test_a_stale_value_is_judged_too() -> None:
    """A frame that arrived after the last cycle changed cable 2's value without counting
    as this cycle's sample (its real answer is late): the controller would use it, so it
    is judged like any other."""
    trust = trusted_at_home()
    sample = lengths_at()
    sample[2] = 4.1
    stale = [True] * 8
    stale[2] = False
    assert [f.cable for f in trust.check(sample, STILL, stale, PERIOD)] == [2]
    assert trust.held == lengths_at()


@pytest.mark.parametrize("follow", ["at_once", "next_tick"])
def test_far_from_where_it_was_linearised_the_check_follows_the_pose(follow: str) -> None:
    """Far from where it was linearised the null space no longer removes a rigid motion:
    a long fast move looks inconsistent after a while, unless the check follows the
    measured pose as the service makes it do every cycle (linearised at the next tick);
    then even a 14 ms gap (14 mm at 1 m/s) 0.6 m away is trusted."""
    velocity = (1.0, -0.5, 0.5, 0.3)
    with pytest.raises(AssertionError):
        moving(velocity, cycles=300)
    trust, at, t = moving(velocity, cycles=300, follow=follow)
    sample, rates, _ = step_on(at, velocity, dt=0.014)
    assert trust.check(sample, rates, FRESH, t + 0.014) == []


def test_retrust_judges_the_next_set_afresh_and_keeps_the_hold_until_then() -> None:
    trust = trusted_at_home()
    settled = lengths_at()
    settled[0] += 2e-3  # the set changed at rest (a tension transient, say)
    assert [f.cable for f in trust.check(settled, STILL, FRESH, PERIOD)] == [0]
    trust.retrust()
    assert trust.held == lengths_at()
    assert trust.check(settled, STILL, FRESH, 2 * PERIOD) == []  # fits one pose closely
    assert trust.held == settled
    forged = lengths_at()
    forged[0] = 4.1
    trust.retrust()
    [problem] = trust.check(forged, STILL, FRESH, 10.0)
    assert 0 in named(problem)
    assert trust.held == settled
    # one attempt: afterwards an offset that would fit one pose is judged as before
    offset = list(settled)
    offset[0] += 2e-3
    assert [f.cable for f in trust.check(offset, STILL, FRESH, 10.0 + RETRY)] == [0]
    assert trust.held == settled


def test_a_retrust_not_yet_judged_can_be_dropped(reference8: Robot) -> None:
    """A reset that gave up waiting drops its retrust: the trusted set and its checks
    stand, and a cable off by 1.5 mm is not trusted afresh later."""
    trust = TrustedLengths(
        reference8,
        list(range(1, 9)),
        max_speed=3.0,
        tolerance=1e-3,
        slack=0.014,
        rest_tensions=[0.0] * 8,
    )
    lengths = reference8.cable_lengths(reference8.home).tolist()
    assert trust.check(lengths, [0.0] * 8, [True] * 8, 0.0) == []
    assert not trust.retrusting
    trust.retrust()
    assert trust.retrusting
    trust.cancel_retrust()
    assert not trust.retrusting
    off = [lengths[0] + 1.5e-3, *lengths[1:]]
    [problem] = trust.check(off, [0.0] * 8, [True] * 8, 0.002)
    assert problem.cable == 0
    assert trust.held == lengths


def swaying(t: float) -> tuple[list[float], list[float]]:
    """Lengths and rates at t of the platform swaying along x, 1 cm at 3 Hz (3.6 m/s^2 at
    its turns, inside the default trajectory limits)."""
    w = 2 * math.pi * 3.0
    x, v, h = 0.01 * math.sin(w * t), 0.01 * w * math.cos(w * t), 1e-6
    now = lengths_at(x)
    return now, rates_between(lengths_at(x - v * h), lengths_at(x + v * h), 2 * h)


def trusted_swaying(max_accel: float, t: float) -> TrustedLengths:
    trust = make(max_accel)
    assert trust.check(*swaying(t), FRESH, t) == []
    return trust


BOUND = cable_accel_bound(TrajectoryLimits(), ROBOT.geometry.attachments, 0.3)


def test_after_a_long_gap_a_cable_that_turned_round_is_not_a_false_brake() -> None:
    """150 ms between two trusted samples (a stalled host) in which the sway turned:
    the end rates' mean says little about the way moved.  Without the acceleration's
    allowance that was a false brake; with it, no cable is named."""
    t0, t1 = 0.02, 0.17
    without = trusted_swaying(0.0, t0).check(*swaying(t1), FRESH, t1)
    assert without and "where its rate gives" in without[0].reason
    assert trusted_swaying(BOUND, t0).check(*swaying(t1), FRESH, t1) == []


def test_over_one_cycle_the_allowance_stays_a_few_micrometres() -> None:
    """At 500 Hz the acceleration adds max_accel x (2 ms)^2 / 4 to the tolerance: a cable
    at the sway's turn (at rest) that jumps 1.1 mm is still named by its own rate."""
    assert 0.25 * BOUND * PERIOD**2 < 3e-5
    turn = 1 / 12  # s: a quarter of the sway's period
    trust = trusted_swaying(BOUND, turn)
    sample, rates = swaying(turn + PERIOD)
    sample[2] += 1.1e-3
    [problem] = trust.check(sample, rates, FRESH, turn + PERIOD)
    assert problem.cable == 2 and "where its rate gives" in problem.reason


def test_the_cable_accel_bound_holds_along_random_motions_within_the_limits() -> None:
    """The second derivative of every cable's length (central differences of the robot's
    own cable_lengths) along 300 random motions at the trajectory limits' rates, from
    random poses about home, stays within cable_accel_bound."""
    limits = TrajectoryLimits()
    rng = np.random.default_rng(7)
    h = 1e-4

    def within(bound: float) -> np.ndarray:
        u = rng.normal(size=3)
        return u / np.linalg.norm(u) * bound * rng.uniform(0.5, 1.0)

    worst, shortest = 0.0, math.inf
    for _ in range(300):
        p = ROBOT.home.position + rng.uniform(-0.3, 0.3, 3)
        r0 = rng.normal(size=3) * 0.2
        v, a = within(limits.linear_speed), within(limits.linear_accel)
        w, alpha = within(limits.angular_speed), within(limits.angular_accel)
        base = Pose.from_rotvec(p, r0)

        def at(t: float, base=base, p=p, v=v, a=a, w=w, alpha=alpha) -> np.ndarray:
            turn = Pose.from_rotvec(np.zeros(3), w * t + 0.5 * alpha * t * t)
            rotation = turn.rotation @ base.rotation
            pose = Pose.from_matrix(p + v * t + 0.5 * a * t * t, rotation)
            return ROBOT.cable_lengths(pose)

        second = (at(h) - 2 * at(0.0) + at(-h)) / (h * h)
        worst = max(worst, float(np.max(np.abs(second))))
        shortest = min(shortest, float(np.min(at(0.0))))
    bound = cable_accel_bound(limits, ROBOT.geometry.attachments, shortest)
    assert worst <= bound, (worst, bound)
    assert worst > 0.3 * bound  # the motions came near it: the check checks something


def test_a_cable_refused_while_the_others_are_trusted_gets_no_acceleration_allowance() -> None:
    """A forger's frames keep one cable refused while the others are trusted: its trusted
    sample ages, but the allowance for acceleration is only for gaps no set was trusted
    in, so a value 5 mm off with rate 0 is named by its own rate 200 ms on (with the
    allowance it would pass: 20 m/s^2 x (0.2 s)^2 / 4 = 0.2 m)."""
    t = 1 / 12  # the sway's turn: at rest
    trust = trusted_swaying(BOUND, t)
    sample, rates = swaying(t)[0], [0.0] * 8
    for _ in range(100):
        t += PERIOD
        forged = list(sample)
        forged[3] += 0.05  # far beyond the step bound: refused every cycle
        [problem] = trust.check(forged, rates, FRESH, t)
        assert problem.cable == 3
    forged = list(sample)
    forged[3] += 5e-3
    problems = trust.check(forged, rates, FRESH, t + PERIOD)
    assert [p.cable for p in problems] == [3] and "where its rate gives" in problems[0].reason


def gap_move(
    move: tuple[float, float, float, float], gap: float = 0.15
) -> tuple[TrustedLengths, list[float], list[float], list[float]]:
    """A trust that saw the platform leave home at constant velocity and then lost
    `gap` s of samples (a stalled host) over which it moved `move` ((dx, dy, dz) m, rz
    rad) in all: (trust, the change since the trusted set, the new lengths, their rates)."""
    velocity = tuple(m / gap for m in move)
    trust = make(BOUND)
    assert trust.check(lengths_at(), STILL, FRESH, 0.0) == []
    at = [v * PERIOD for v in velocity]
    first = lengths_at(*at)
    assert trust.check(first, rates_between(lengths_at(), first, PERIOD), FRESH, PERIOD) == []
    trust.follow_pose(Pose.from_rotvec(ROBOT.home.position + np.array(at[:3]), [0, 0, at[3]]))
    sample, rates, _ = step_on(at, velocity, gap)
    return trust, [b - a for a, b in zip(first, sample, strict=True)], sample, rates


@pytest.mark.parametrize(
    "move", [(0.07, 0.0, 0.0, 0.0), (0.0, 0.06, -0.04, 0.0), (0.07, 0.03, 0.05, 0.1)]
)
def test_a_long_rigid_move_between_trusted_sets_is_not_a_false_brake(
    move: tuple[float, float, float, float],
) -> None:
    """7-10 cm (and 0.1 rad) between two trusted sets: the linear check alone errs by
    more than the tolerance there (asserted), the second look fits both sets and trusts
    the new one."""
    trust, change, sample, rates = gap_move(move)
    assert max(trust._residuals(change)) > TOLERANCE  # what braked flights after gaps
    assert max(map(abs, change)) > trust.linear_reach
    assert trust.check(sample, rates, FRESH, PERIOD + 0.15) == []
    assert trust.held == sample


@pytest.mark.parametrize(("cable", "offset"), [(1, 3e-3), (5, -3e-3), (2, 2.5e-3)])
def test_a_forged_cable_after_a_long_move_is_still_named(cable: int, offset: float) -> None:
    """The same long move with one cable 2.5-3 mm off (a forged frame, a slipped drum):
    the second look's residual on it is what the offset leaves in the left null space
    (half of it: |N_k| is 0.5 on reference8 near home), beyond the tolerance (asserted),
    and the cable is named, nothing trusted."""
    trust, _, sample, rates = gap_move((0.0, 0.06, -0.04, 0.0))
    before = list(trust.held)
    seen = abs(offset) / trust._inverse_norms[cable]  # |N_k| e: what a fit cannot absorb
    assert seen > 1.2 * TOLERANCE
    sample[cable] += offset
    faults = trust.check(sample, rates, FRESH, PERIOD + 0.15)
    assert cable in set().union(*map(named, faults))
    assert trust.held == before


@settings(max_examples=40, deadline=None)
@given(
    move=st.tuples(*[st.floats(-0.08, 0.08)] * 3, st.floats(-0.1, 0.1)),
    cable=st.integers(0, 7),
    offset=st.floats(4 * TOLERANCE, 0.01) | st.floats(-0.01, -4 * TOLERANCE),
)
def test_over_any_long_move_rigid_sets_are_trusted_and_an_outlier_is_named(
    move: tuple[float, float, float, float], cable: int, offset: float
) -> None:
    trust, _, sample, rates = gap_move(move)
    assert trust.check(sample, rates, FRESH, PERIOD + 0.15) == []
    trust, _, sample, rates = gap_move(move)
    sample[cable] += offset
    faults = trust.check(sample, rates, FRESH, PERIOD + 0.15)
    assert cable in set().union(*map(named, faults))


def test_a_failed_second_look_waits_before_the_next(monkeypatch: pytest.MonkeyPatch) -> None:
    """A cable really off fails the second look; the next RETRY s judge linearly only
    (two fits a cycle would cost the loop its period), then a second look again."""
    trust, _, sample, rates = gap_move((0.0, 0.06, -0.04, 0.0))
    fits = []
    fit = ROBOT.forward_kinematics
    monkeypatch.setattr(ROBOT, "forward_kinematics", lambda *a: fits.append(a) or fit(*a))
    forged = list(sample)
    forged[1] += 5e-3
    t = PERIOD + 0.15
    assert trust.check(forged, rates, FRESH, t) and len(fits) == 2
    assert trust.check(forged, rates, FRESH, t + 0.5 * RETRY) and len(fits) == 2
    assert trust.check(sample, rates, FRESH, t + RETRY) == [] and len(fits) == 4
