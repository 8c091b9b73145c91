"""Reference trajectories: the curve, its rates, limits, parsing and transitions."""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import make_interp_spline

from cdpr import Pose, Robot, liediff
from cdpr.so3 import exp_so3, hat, quat4_to_rotvec, quats_to_rotvecs, vee
from cdpr.trajectory import (
    Reference,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    Waypoint,
    approach,
    approach_steps,
    core,
    goto,
    parse_trajectory,
    rotation,
    run_steps,
    stop_steps,
    transitions,
    validate,
    validation_steps,
)
from cdpr.trajectory.core import MIN_SEGMENT, Curve
from cdpr.trajectory.jerk import jerk_excess
from cdpr.trajectory.limits import MAX_WAYPOINTS
from cdpr.trajectory.parse import _waypoint
from cdpr.trajectory.rotation import angular_rates, left_jacobians
from cdpr.trajectory.transitions import MIN_BLEND

LIMITS = TrajectoryLimits()
HOME = np.array([0.0, 0.0, 1.25])
ZERO6 = np.zeros(6)


def random_waypoints(seed: int, n: int = 6, reach: float = 1.0, tilt: float = 1.5) -> list:
    """n waypoints 0.5 .. 2 s apart at random positions and orientations."""
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.5, 2.0, n)) - 1.0
    return [
        Waypoint(t, Pose.from_rotvec(rng.uniform(-reach, reach, 3), rng.uniform(-tilt, tilt, 3)))
        for t in times
    ]


def with_interior_twists(waypoints: list, seed: int) -> list:
    """The same waypoints with a random twist (and at one, an accel) at interior ones."""
    rng = np.random.default_rng(seed)
    out = [waypoints[0]]
    for k, w in enumerate(waypoints[1:-1], start=1):
        accel = rng.normal(0.0, 0.5, 6) if k == 2 else None
        out.append(Waypoint(w.t, w.pose, rng.normal(0.0, 0.5, 6), accel))
    return [*out, waypoints[-1]]


def moving_start(waypoints: list, seed: int) -> list:
    rng = np.random.default_rng(seed)
    w = waypoints[0]
    return [Waypoint(w.t, w.pose, rng.normal(0, 0.5, 6), rng.normal(0, 1.0, 6)), *waypoints[1:]]


def large_turns() -> list:
    """Turns of 170 degrees about a different axis in each segment."""
    axes = np.array([[0.3, -0.5, 0.81], [1.0, 0.0, 0.0], [0.0, 0.6, -0.8]])
    R = np.eye(3)
    out = [Waypoint(0.0, Pose(HOME))]
    for k, axis in enumerate(axes):
        R = exp_so3(np.deg2rad(170.0) * axis / np.linalg.norm(axis)) @ R
        out.append(Waypoint(1.5 * (k + 1), Pose.from_matrix(HOME, R)))
    return out


TRAJECTORIES = {
    "plain": lambda: Trajectory(random_waypoints(1)),
    "interior_twists": lambda: Trajectory(with_interior_twists(random_waypoints(2), 3)),
    "moving_start": lambda: Trajectory(moving_start(random_waypoints(4), 5)),
    # consecutive orientations about 170 degrees apart: log near pi in every segment
    "large_turns": lambda: Trajectory(large_turns()),
}


@pytest.fixture(params=sorted(TRAJECTORIES))
def trajectory(request: pytest.FixtureRequest) -> Trajectory:
    return TRAJECTORIES[request.param]()


def inner_times(tr: Trajectory, n: int = 60) -> np.ndarray:
    """n instants inside the trajectory, off the knots (where the jerk may jump)."""
    times = tr.start_time + tr.duration * (np.arange(1, n + 1) + 0.37) / (n + 1)
    knots = np.array([w.t for w in tr.waypoints])
    assert np.abs(times[:, None] - knots).min() > 1e-3
    return times


def fd_twist(tr: Trajectory, t: float, h: float = 1e-5) -> np.ndarray:
    return liediff(tr.sample(t - h).pose, tr.sample(t + h).pose) / (2 * h)


def fd_accel(tr: Trajectory, t: float, h: float = 1e-4) -> np.ndarray:
    """Second central difference on the group: (η+ ⊖ η) + (η- ⊖ η) = h² α + O(h⁴)."""
    mid = tr.sample(t).pose
    return (liediff(mid, tr.sample(t + h).pose) + liediff(mid, tr.sample(t - h).pose)) / h**2


def peak_rates(tr: Trajectory, n: int = 4000) -> dict[str, float]:
    refs = [tr.sample(t) for t in np.linspace(tr.start_time, tr.end_time, n)]
    tw = np.array([r.twist for r in refs])
    ac = np.array([r.accel for r in refs])
    norm = np.linalg.norm
    return {
        "linear_speed": float(norm(tw[:, :3], axis=1).max()),
        "angular_speed": float(norm(tw[:, 3:], axis=1).max()),
        "linear_accel": float(norm(ac[:, :3], axis=1).max()),
        "angular_accel": float(norm(ac[:, 3:], axis=1).max()),
    }


def assert_within(peaks: dict[str, float], limits: TrajectoryLimits) -> None:
    for name, value in peaks.items():
        assert value <= getattr(limits, name), (name, value)


def assert_same_state(a: Reference, b: Reference, tol: float) -> None:
    assert np.abs(liediff(a.pose, b.pose)).max() < tol
    np.testing.assert_allclose(a.twist, b.twist, atol=tol)
    np.testing.assert_allclose(a.accel, b.accel, atol=tol)


# -- the curve ----------------------------------------------------------------------------


def test_waypoints_are_interpolated_exactly(trajectory: Trajectory) -> None:
    for w in trajectory.waypoints:
        ref = trajectory.sample(w.t)
        assert np.abs(liediff(ref.pose, w.pose)).max() < 1e-12
        if w.twist is not None:
            np.testing.assert_allclose(ref.twist, w.twist, atol=1e-12)
        if w.accel is not None:
            np.testing.assert_allclose(ref.accel, w.accel, atol=1e-12)


def test_twist_and_accel_match_finite_differences(trajectory: Trajectory) -> None:
    for t in inner_times(trajectory):
        ref = trajectory.sample(t)
        np.testing.assert_allclose(ref.twist, fd_twist(trajectory, t), atol=1e-6)
        np.testing.assert_allclose(ref.accel, fd_accel(trajectory, t), atol=1e-4)


def test_omega_is_the_world_frame_rate(trajectory: Trajectory) -> None:
    """Ṙ = [ω]× R from differences of rotation matrices; the body rate differs."""
    h = 1e-6
    differs = 0.0
    for t in inner_times(trajectory, 20):
        R = trajectory.sample(t).pose.rotation
        R_dot = trajectory.sample(t + h).pose.rotation - trajectory.sample(t - h).pose.rotation
        R_dot /= 2 * h
        omega = trajectory.sample(t).twist[3:]
        np.testing.assert_allclose(vee(R_dot @ R.T), omega, atol=1e-7)
        differs = max(differs, float(np.abs(vee(R.T @ R_dot) - omega).max()))
    assert differs > 0.1  # the test would notice a body-frame omega


def test_omega_dot_is_the_derivative_of_the_world_rate(trajectory: Trajectory) -> None:
    h = 1e-5
    for t in inner_times(trajectory, 20):
        fd = (trajectory.sample(t + h).twist - trajectory.sample(t - h).twist) / (2 * h)
        np.testing.assert_allclose(trajectory.sample(t).accel, fd, atol=1e-5)


def test_c2_across_knots(trajectory: Trajectory) -> None:
    for w in trajectory.waypoints[1:-1]:
        left = trajectory.sample(math.nextafter(w.t, -math.inf))
        right = trajectory.sample(w.t)
        assert_same_state(left, right, 1e-9)
        # and just around it, the acceleration moves by no more than jerk * time
        eps = 1e-7
        jump = trajectory.sample(w.t + eps).accel - trajectory.sample(w.t - eps).accel
        assert np.abs(jump).max() < 1e-3


def test_rest_at_both_ends_and_hold_after_the_end() -> None:
    tr = Trajectory(random_waypoints(7))
    first, last = tr.waypoints[0], tr.waypoints[-1]
    for t in (tr.start_time, tr.end_time, tr.end_time + 5.0, 1e12):
        ref = tr.sample(t)
        assert not ref.twist.any() and not ref.accel.any()
    for t in (tr.start_time - 1.0, -1e12):
        ref = tr.sample(t)
        assert ref.pose == first.pose and not ref.twist.any() and not ref.accel.any()
    assert tr.sample(tr.end_time + 3.0).pose == last.pose
    # no jump arriving at the end: the state just before the end is the last pose at rest
    just_before = tr.sample(math.nextafter(tr.end_time, 0.0))
    assert_same_state(just_before, Reference(last.pose, ZERO6, ZERO6), 1e-9)
    just_after = tr.sample(math.nextafter(tr.start_time, tr.end_time))
    assert_same_state(just_after, Reference(first.pose, ZERO6, ZERO6), 1e-9)
    with pytest.raises(ValueError, match="number"):
        tr.sample(float("nan"))


def test_positions_are_the_quintic_interpolating_spline() -> None:
    """Minimum jerk with no interior twists is the C⁴ quintic spline through the points."""
    wps = random_waypoints(8, n=9)
    tr = Trajectory(wps)
    times = [w.t for w in wps]
    rest = [(1, np.zeros(3)), (2, np.zeros(3))]
    spline = make_interp_spline(times, [w.pose.position for w in wps], k=5, bc_type=(rest, rest))
    for t in np.linspace(times[0], times[-1], 200):
        ref = tr.sample(t)
        np.testing.assert_allclose(ref.pose.position, spline(t), atol=1e-12)
        np.testing.assert_allclose(ref.twist[:3], spline(t, 1), atol=1e-11)
        np.testing.assert_allclose(ref.accel[:3], spline(t, 2), atol=1e-10)


def test_single_axis_rotation_is_the_quintic_spline_of_the_angle() -> None:
    """About one fixed axis, rotations commute: ω is the spline of the angle's rate."""
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    times, angles = [0.0, 1.0, 2.5, 3.0, 4.2], [0.0, 1.0, -0.5, 0.3, 2.0]
    tr = Trajectory(
        [Waypoint(t, Pose.from_rotvec(HOME, a * axis)) for t, a in zip(times, angles, strict=True)]
    )
    rest = [(1, 0.0), (2, 0.0)]
    spline = make_interp_spline(times, angles, k=5, bc_type=(rest, rest))
    for t in np.linspace(0.0, 4.2, 50):
        ref = tr.sample(t)
        np.testing.assert_allclose(ref.pose.rotation, exp_so3(spline(t) * axis), atol=1e-12)
        np.testing.assert_allclose(ref.twist[3:], spline(t, 1) * axis, atol=1e-11)
        np.testing.assert_allclose(ref.accel[3:], spline(t, 2) * axis, atol=1e-10)


def test_shifted_moves_every_time() -> None:
    tr = Trajectory(with_interior_twists(random_waypoints(9), 10))
    moved = tr.shifted(100.25)
    assert moved.start_time == tr.start_time + 100.25 and moved.duration == pytest.approx(
        tr.duration
    )
    assert [w.t for w in moved.waypoints] == [w.t + 100.25 for w in tr.waypoints]
    for t in inner_times(tr, 15):
        assert_same_state(moved.sample(t + 100.25), tr.sample(t), 1e-9)


def test_knots_hold_the_full_state() -> None:
    tr = Trajectory(random_waypoints(11))
    for knot in tr.knots:
        ref = tr.sample(knot.t)
        np.testing.assert_allclose(knot.twist, ref.twist, atol=1e-12)
        np.testing.assert_allclose(knot.accel, ref.accel, atol=1e-12)
    # rebuilding from the full knot states reproduces the curve
    again = Trajectory(tr.knots)
    for t in inner_times(tr, 15):
        assert_same_state(again.sample(t), tr.sample(t), 1e-10)


def knot_arrays(tr: Trajectory) -> list[np.ndarray]:
    """(times, positions, quaternions, twists, accels) of a trajectory's knots."""
    knots = tr.knots
    return [
        np.array([k.t for k in knots]),
        np.array([k.pose.position for k in knots]),
        np.array([k.pose.quaternion for k in knots]),
        np.array([k.twist for k in knots]),
        np.array([k.accel for k in knots]),
    ]


def test_a_trajectory_through_arrays_is_the_one_through_their_waypoints() -> None:
    """Trajectory.through (a timed path's thousands of knots, no Waypoint made) builds the
    curve Trajectory builds from the same knots as Waypoints; its waypoints, made when
    asked, are those knots.  A quaternion given with w < 0 (the same rotation) or a
    hair off unit is stored as a Pose stores it."""
    tr = Trajectory(random_waypoints(31))
    times, positions, quats, twists, accels = knot_arrays(tr)
    signed = quats * np.where(np.arange(len(quats)) % 2, -1.0, 1.0)[:, None] * (1.0 + 1e-7)
    through = Trajectory.through(times, positions, signed, twists, accels)
    assert len(through) == len(tr) and through.duration == tr.duration
    for t in inner_times(tr, 25):
        assert_same_state(through.sample(t), tr.sample(t), 1e-12)
    for made, knot in zip(through.waypoints, tr.knots, strict=True):
        assert made.t == knot.t and made.pose.position_tuple == knot.pose.position_tuple
        np.testing.assert_allclose(made.pose.quaternion, knot.pose.quaternion, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(made.twist, knot.twist)
        np.testing.assert_array_equal(made.accel, knot.accel)
    # the arrays are copied: changing the caller's afterwards changes nothing
    twists[1] += 1.0
    assert not np.array_equal(through.waypoints[1].twist, twists[1])


def test_a_trajectory_through_arrays_names_a_bad_knot() -> None:
    times, positions, quats, twists, accels = knot_arrays(Trajectory(random_waypoints(32)))

    def refused(**change: np.ndarray) -> TrajectoryError:
        given = {"times": times, "positions": positions, "quaternions": quats}
        given |= {"twists": twists, "accels": accels} | change
        with pytest.raises(TrajectoryError) as info:
            Trajectory.through(**given)
        return info.value

    off_unit = quats.copy()
    off_unit[2] *= 1.01
    err = refused(quaternions=off_unit)
    assert (err.waypoint, err.limit, err.field) == (2, "unit_quaternion", "waypoints[2].quaternion")
    nan_twist = twists.copy()
    nan_twist[3, 4] = np.nan
    err = refused(twists=nan_twist)
    assert (err.waypoint, err.limit, err.field) == (3, "finite", "waypoints[3].twist")
    late = times.copy()
    late[4] = late[3]
    assert (refused(times=late).waypoint, refused(times=late).limit) == (4, "times_increasing")
    moving = twists.copy()
    moving[-1, 0] = 0.1
    assert refused(twists=moving).limit == "end_at_rest"
    assert refused(accels=accels[:, :3]).limit == "schema"
    assert refused(times=times[:1], positions=positions[:1]).limit == "min_waypoints"


def test_left_jacobian_is_the_derivative_of_exp() -> None:
    """exp(θ + ε δ) exp(θ)ᵀ ≈ exp(ε J_l(θ) δ), across the series/closed-form switch."""
    rng = np.random.default_rng(12)
    for size in (0.0, 1e-6, 0.19999, 0.2, 0.20001, 1.0, 3.1, 5.0):
        theta = size * np.array([0.6, -0.8, 0.0])
        delta = rng.normal(size=3)
        eps = 1e-6
        R_dot = (exp_so3(theta + eps * delta) - exp_so3(theta - eps * delta)) / (2 * eps)
        J = left_jacobians([theta])[0]
        np.testing.assert_allclose(vee(R_dot @ exp_so3(theta).T), J @ delta, atol=1e-8)
        # ω̇ = J θ̈ + J̇ θ̇: J̇ θ̇ against a difference of J along θ + t θ̇
        dot = rng.normal(size=3)
        ahead, behind = left_jacobians([theta + eps * dot, theta - eps * dot])
        J_dot = (ahead - behind) / (2 * eps)
        _, omega_dot = angular_rates(theta, dot, [0.0, 0.0, 0.0])
        np.testing.assert_allclose(omega_dot, J_dot @ dot, atol=1e-8)


# -- construction errors ------------------------------------------------------------------


def test_times_must_increase() -> None:
    wps = random_waypoints(13)
    bad = [*wps[:3], Waypoint(wps[2].t, wps[3].pose), *wps[4:]]
    with pytest.raises(TrajectoryError) as info:
        Trajectory(bad)
    err = info.value
    assert (err.waypoint, err.limit, err.value) == (3, "times_increasing", wps[2].t)
    assert str(err).startswith("waypoint 3: times_increasing")
    with pytest.raises(TrajectoryError, match="times_increasing"):
        Trajectory([wps[0], Waypoint(wps[0].t + MIN_SEGMENT / 2, wps[1].pose)])


def test_a_trajectory_needs_two_waypoints_and_must_end_at_rest() -> None:
    wps = random_waypoints(14, n=3)
    with pytest.raises(TrajectoryError) as info:
        Trajectory(wps[:1])
    assert info.value.limit == "min_waypoints"
    moving_end = [*wps[:2], Waypoint(wps[2].t, wps[2].pose, [0.0, 0.1, 0.0, 0.0, 0.0, 0.0])]
    with pytest.raises(TrajectoryError) as info:
        Trajectory(moving_end)
    assert (info.value.waypoint, info.value.limit) == (2, "end_at_rest")
    assert info.value.value == pytest.approx(0.1)
    # an explicit zero twist at the end is fine
    Trajectory([*wps[:2], Waypoint(wps[2].t, wps[2].pose, ZERO6, ZERO6)])


def test_non_finite_rates_and_times_are_rejected() -> None:
    wps = random_waypoints(15, n=3)
    twist = np.array([0.0, np.nan, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(TrajectoryError) as info:
        Trajectory([wps[0], Waypoint(wps[1].t, wps[1].pose, twist), wps[2]])
    assert (info.value.waypoint, info.value.limit, info.value.field) == (
        1,
        "finite",
        "waypoints[1].twist",
    )
    with pytest.raises(TrajectoryError) as info:
        Trajectory([wps[0], Waypoint(math.inf, wps[1].pose)])
    assert (info.value.waypoint, info.value.limit) == (1, "finite")


# -- the interface form -------------------------------------------------------------------


def doc(*waypoints: dict, **extra: object) -> dict:
    return {"waypoints": list(waypoints), **extra}


def wp(t: float, x: float = 0.0, **extra: object) -> dict:
    return {
        "t": t,
        "position": [x, 0.0, 1.25],
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},
        **extra,
    }


def rejected(data: object, limits: TrajectoryLimits = LIMITS) -> TrajectoryError:
    with pytest.raises(TrajectoryError) as info:
        parse_trajectory(data, limits)
    return info.value


def test_parse_round_trips_as_dict() -> None:
    tr = Trajectory(moving_start(with_interior_twists(random_waypoints(16), 17), 18))
    data = tr.as_dict()
    assert data["version"] == 1 and set(data["waypoints"][0]["quaternion"]) == set("wxyz")
    again = parse_trajectory(data)
    for t in inner_times(tr, 20):
        assert_same_state(again.sample(t), tr.sample(t), 1e-9)


def test_parse_accepts_position_objects_and_normalises_near_unit_quaternions() -> None:
    q = {"w": 1.0 + 5e-7, "x": 0.0, "y": 0.0, "z": 0.0}
    tr = parse_trajectory(
        doc(
            {"t": 0.0, "position": {"x": 0.0, "y": 0.0, "z": 1.25}, "quaternion": q},
            wp(2.0, 0.1, twist={"linear": [0, 0, 0], "angular": {"x": 0, "y": 0, "z": 0}}),
            version=1,
        )
    )
    assert tr.waypoints[0].pose.quaternion.tolist() == [1.0, 0.0, 0.0, 0.0]
    assert tr.sample(2.0).pose.position.tolist() == [0.1, 0.0, 1.25]


def test_parse_rejects_a_non_unit_quaternion() -> None:
    bad = wp(1.0, 0.1)
    bad["quaternion"] = {"w": 0.9, "x": 0.0, "y": 0.0, "z": 0.0}
    err = rejected(doc(wp(0.0), bad))
    assert (err.waypoint, err.limit, err.field) == (1, "unit_quaternion", "waypoints[1].quaternion")
    assert err.value == pytest.approx(0.9)
    assert "waypoint 1" in str(err) and "0.9" in str(err)
    # within a looser configured tolerance it is normalised instead
    bad["quaternion"] = {"w": 0.0, "x": 0.0, "y": 0.0, "z": 1.005}
    assert rejected(doc(wp(0.0), bad)).limit == "unit_quaternion"
    tr = parse_trajectory(doc(wp(0.0), bad), TrajectoryLimits(unit_tolerance=0.01))
    assert tr.waypoints[1].pose.quaternion.tolist() == [0.0, 0.0, 0.0, 1.0]


def test_parse_rejects_nan_with_the_waypoint_and_field() -> None:
    bad = wp(1.0)
    bad["position"] = [0.0, float("nan"), 1.25]
    err = rejected(doc(wp(0.0), wp(0.5), bad))
    assert (err.waypoint, err.limit, err.field) == (2, "finite", "waypoints[2].position[1]")
    assert math.isnan(err.value) and "nan" in str(err)


def test_parse_rejects_non_increasing_times() -> None:
    err = rejected(doc(wp(0.0), wp(1.0, 0.1), wp(1.0, 0.2)))
    assert (err.waypoint, err.limit, err.value) == (2, "times_increasing", 1.0)


def test_plain_waypoints_read_in_bulk_make_the_trajectory_one_by_one_would() -> None:
    """Waypoints all of the plain form go to Trajectory.through as arrays; one written
    otherwise (a position object) sends every one through Waypoint: the same curve, the
    same waypoints, and the same error named at the same waypoint."""
    rng = np.random.default_rng(41)
    plain = []
    for k in range(30):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= 1.0 + 1e-8  # within the unit tolerance, normalised on parsing
        quaternion = dict(zip("wxyz", q.tolist(), strict=True))
        plain.append({"t": 0.5 * k, "position": rng.uniform(-1, 1, 3).tolist(),
                      "quaternion": quaternion})  # fmt: skip
    x, y, z = plain[3]["position"]
    mixed = [*plain[:3], {**plain[3], "position": {"x": x, "y": y, "z": z}}, *plain[4:]]
    bulk, single = parse_trajectory(doc(*plain)), parse_trajectory(doc(*mixed))
    assert bulk._knots._listed is None and single._knots._listed is not None  # the two routes
    for t in np.linspace(-0.5, 15.0, 97):
        assert_same_state(bulk.sample(float(t)), single.sample(float(t)), 1e-12)
    for a, b in zip(bulk.waypoints, single.waypoints, strict=True):
        assert (a.t, a.twist, a.accel) == (b.t, None, None)
        assert a.pose.position_tuple == b.pose.position_tuple
        np.testing.assert_allclose(a.pose.quaternion, b.pose.quaternion, rtol=0, atol=1e-15)
    late = [*plain[:7], {**plain[7], "t": plain[6]["t"]}, *plain[8:]]
    errors = [rejected(doc(*late)), rejected(doc(*late[:3], mixed[3], *late[4:]))]
    assert errors[0].args == errors[1].args and errors[0].waypoint == 7


def test_parse_rejects_too_many_waypoints() -> None:
    limits = TrajectoryLimits(max_waypoints=5)
    err = rejected(doc(*(wp(float(i)) for i in range(6))), limits)
    assert (err.limit, err.value) == ("max_waypoints", 6.0)
    assert "6 waypoints exceed the limit of 5" in str(err)
    parse_trajectory(doc(*(wp(float(i)) for i in range(5))), limits)


@pytest.mark.parametrize(
    ("mutate", "limit", "field"),
    [
        (lambda w: w.update(speed=1.0), "schema", "waypoints[1]"),
        (lambda w: w.pop("t"), "schema", "waypoints[1].t"),
        (lambda w: w.update(t="1.0"), "schema", "waypoints[1].t"),
        (lambda w: w.update(t=True), "schema", "waypoints[1].t"),
        (lambda w: w.update(t=10**400), "finite", "waypoints[1].t"),
        (lambda w: w.update(t=1e12), "finite", "waypoints[1].t"),
        (lambda w: w.update(position=[0.0, 1.25]), "schema", "waypoints[1].position"),
        (lambda w: w.update(position=[0.0, 1e7, 1.25]), "finite", "waypoints[1].position"),
        (lambda w: w.update(quaternion=[1.0, 0.0, 0.0, 0.0]), "schema", "waypoints[1].quaternion"),
        (lambda w: w["quaternion"].pop("z"), "schema", "waypoints[1].quaternion.z"),
        (lambda w: w.update(twist=[0.0] * 6), "schema", "waypoints[1]"),
        (lambda w: w.update(twist={"linear": [0, 0, 0]}), "schema", "waypoints[1].twist.angular"),
    ],
)
def test_parse_rejects_malformed_waypoints(mutate, limit: str, field: str) -> None:
    bad = wp(1.0, 0.1)
    mutate(bad)
    err = rejected(doc(wp(0.0), bad, wp(2.0)))
    assert (err.waypoint, err.limit) == (1, limit)
    assert err.field is not None and err.field.startswith(field)


@pytest.mark.parametrize(
    "data", [None, [], "waypoints", {"waypoints": {}}, {"waypoints": []}, {"wp": []}]
)
def test_parse_rejects_malformed_documents(data: object) -> None:
    assert rejected(data).limit in {"schema", "min_waypoints"}


def test_parse_rejects_an_unknown_version() -> None:
    assert rejected(doc(wp(0.0), wp(1.0), version=2)).field == "version"


JSON_SCALARS = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(10**400), max_value=10**400)
    | st.floats()
    | st.text(max_size=4)
)
JSON = st.recursive(
    JSON_SCALARS,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)
NUMBER = st.floats() | st.integers(min_value=-(10**400), max_value=10**400) | JSON_SCALARS
VEC3 = st.lists(NUMBER, min_size=2, max_size=4) | st.fixed_dictionaries(
    {"x": NUMBER, "y": NUMBER, "z": NUMBER}
)
NEAR_VALID_WAYPOINT = st.dictionaries(
    st.sampled_from(["t", "position", "quaternion", "twist", "accel", "w"]),
    st.one_of(
        NUMBER,
        VEC3,
        st.fixed_dictionaries({"w": NUMBER, "x": NUMBER, "y": NUMBER, "z": NUMBER}),
        st.fixed_dictionaries({"linear": VEC3, "angular": VEC3}),
        JSON,
    ),
)
GOOD_WAYPOINT = st.builds(
    lambda t, x, q: wp(t, x) | {"quaternion": dict(zip("wxyz", q, strict=True))},
    st.floats(-1e10, 1e10) | st.integers(-5, 5),
    st.floats(-2, 2),
    st.sampled_from([(1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.5, 0.5, 0.5, 0.5)]),
)


def _well_formed(rows: list) -> dict:
    t, out = 0.0, []
    for gap, x, q, twist in rows:
        t += gap
        item = wp(t, x) | {"quaternion": dict(zip("wxyz", q, strict=True))}
        if twist is not None:
            item["twist"] = {"linear": twist[:3], "angular": twist[3:]}
        out.append(item)
    return {"waypoints": out}


# well-formed documents with extreme but legal numbers: tiny and huge gaps, big rates
WELL_FORMED = st.lists(
    st.tuples(
        st.floats(MIN_SEGMENT, 1e8),
        st.floats(-1e6, 1e6),
        st.sampled_from([(1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (0.5, -0.5, 0.5, 0.5)]),
        st.none() | st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6),
    ),
    min_size=2,
    max_size=6,
).map(_well_formed)


@settings(max_examples=500)
@given(
    st.one_of(
        JSON,
        st.fixed_dictionaries({"waypoints": st.lists(NEAR_VALID_WAYPOINT, max_size=4)}),
        st.fixed_dictionaries(
            {"waypoints": st.lists(GOOD_WAYPOINT | NEAR_VALID_WAYPOINT, max_size=5)},
            optional={"version": JSON_SCALARS},
        ),
        WELL_FORMED,
    )
)
@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
def test_hostile_input_raises_only_trajectory_error(data: object) -> None:
    try:
        tr = parse_trajectory(data)
    except TrajectoryError as err:
        assert err.limit and str(err)
        return
    # whatever was accepted samples to finite values everywhere
    for t in np.linspace(tr.start_time, tr.end_time, 7):
        ref = tr.sample(float(t))
        assert np.all(np.isfinite(ref.pose.position)) and np.all(np.isfinite(ref.twist))
        assert np.all(np.isfinite(ref.accel))


def one_by_one(data: object) -> Trajectory:
    """parse_trajectory as it read every waypoint before the bulk read (parse._waypoint)."""
    assert isinstance(data, dict) and isinstance(data.get("waypoints"), list | tuple)
    raw = data["waypoints"]
    return Trajectory([_waypoint(item, i, LIMITS.unit_tolerance) for i, item in enumerate(raw)])


def outcome(read: Callable[[object], Trajectory], data: object) -> object:
    """The waypoints read (t, position, quaternion, twist, accel), or the error's text."""
    try:
        tr = read(data)
    except TrajectoryError as err:
        return str(err), err.limit, err.waypoint, err.field
    return [
        (w.t, *w.pose.position_tuple, *w.pose.quaternion_tuple, w.twist, w.accel)
        for w in tr.waypoints
    ]


def same_outcome(a: object, b: object) -> bool:
    if isinstance(a, tuple) or isinstance(b, tuple):
        return a == b
    assert isinstance(a, list) and isinstance(b, list) and len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x[:8], y[:8], rtol=1e-15, atol=1e-15)
        for u, v in zip(x[8:], y[8:], strict=True):
            assert (u is None and v is None) or np.array_equal(u, v)
    return True


@settings(max_examples=400)
@given(
    st.fixed_dictionaries({"waypoints": st.lists(GOOD_WAYPOINT | NEAR_VALID_WAYPOINT, max_size=6)})
    | st.fixed_dictionaries({"waypoints": st.lists(GOOD_WAYPOINT, min_size=2, max_size=6)})
    | WELL_FORMED
)
def test_the_bulk_read_decides_as_the_one_by_one_read(data: dict) -> None:
    """Same waypoints, or the same first problem named the same way."""
    assert same_outcome(outcome(parse_trajectory, data), outcome(one_by_one, data))


@pytest.mark.parametrize(
    "bad",
    [True, None, "1", 10**400, math.nan, math.inf, -math.inf, [0.0]],
    ids=["bool", "null", "str", "huge-int", "nan", "inf", "-inf", "list"],
)
@pytest.mark.parametrize("where", ["t", "position", "quaternion"])
def test_a_bad_number_among_plain_waypoints_is_named_by_waypoint_and_field(
    bad: object, where: str
) -> None:
    """A long plain trajectory with one bad number, after a waypoint of another form
    (position as an object): the error names the bad one."""
    waypoints = [wp(0.1 * k, 0.01 * k) for k in range(50)]
    waypoints[3]["position"] = {"x": 0.03, "y": 0.0, "z": 1.25}
    if where == "t":
        waypoints[20]["t"] = bad
    elif where == "position":
        waypoints[20]["position"][1] = bad
    else:
        waypoints[20]["quaternion"]["y"] = bad
    data = doc(*waypoints)
    err = rejected(data)
    assert err.waypoint == 20 and err.field is not None and where in err.field
    assert same_outcome(outcome(parse_trajectory, data), outcome(one_by_one, data))


def test_the_bulk_read_normalises_and_signs_quaternions_as_pose_does() -> None:
    waypoints = [wp(0.0), wp(1.0), wp(2.0)]
    waypoints[1]["quaternion"] = {"w": 0.0, "x": -0.6, "y": 0.8 + 4e-7, "z": 0.0}
    waypoints[2]["quaternion"] = {"w": -1.0 - 3e-7, "x": 0.0, "y": 0.0, "z": 0.0}
    tr = parse_trajectory(doc(*waypoints))
    assert same_outcome(outcome(parse_trajectory, tr.as_dict()), outcome(one_by_one, tr.as_dict()))
    assert same_outcome(outcome(lambda _: tr, None), outcome(one_by_one, doc(*waypoints)))
    assert tr.waypoints[1].pose.quaternion_tuple[1] > 0.0  # w = 0: the first non-zero one
    assert tr.waypoints[2].pose.quaternion_tuple[0] == 1.0


def reference_build(wps: list[Waypoint]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(twists, accels, tables) as the build computed them segment by segment: the jerk
    normal equations assembled and solved densely, each table from liediff, the scalar
    J_l and one Hermite solve."""
    n = len(wps)
    times = np.array([w.t for w in wps])
    steps = [liediff(a.pose, b.pose) for a, b in pairwise(wps)]
    values = np.zeros((n, 6))
    values[:, :3] = [w.pose.position for w in wps]
    values[1:, 3:] = np.cumsum([s[3:] for s in steps], axis=0)
    known = np.zeros((2 * n, 6))
    free = np.zeros(2 * n, dtype=bool)
    for k, w in enumerate(wps):
        for j, vec in enumerate((w.twist, w.accel)):
            if vec is not None:
                known[2 * k + j] = vec
            elif 0 < k < n - 1:
                free[2 * k + j] = True
    H, P = np.zeros((2 * n, 2 * n)), np.zeros((2 * n, n))
    for k in range(n - 1):
        h = times[k + 1] - times[k]
        scale = np.array([1.0, h, h * h, 1.0, h, h * h])
        cost = core._JERK_COST * np.outer(scale, scale) / h**5
        u, y = [2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3], [k, k + 1]
        H[np.ix_(u, u)] += cost[np.ix_([1, 2, 4, 5], [1, 2, 4, 5])]
        P[np.ix_(u, y)] += cost[np.ix_([1, 2, 4, 5], [0, 3])]
    rhs = -(P @ values)[free] - H[np.ix_(free, ~free)] @ known[~free]
    known[free] = np.linalg.solve(H[np.ix_(free, free)], rhs)
    twists, accels = known[0::2], known[1::2]
    tables = []
    for k in range(n - 1):
        delta = steps[k][3:]
        b, c, _, _ = rotation._jl_coefficients(float(delta @ delta))
        W = hat(delta)
        J = np.eye(3) + b * W + c * (W @ W)
        theta_dot1 = np.linalg.solve(J, twists[k + 1][3:])
        _, jdot = angular_rates(delta.tolist(), theta_dot1.tolist(), [0.0, 0.0, 0.0])
        theta_ddot1 = np.linalg.solve(J, accels[k + 1][3:] - np.array(jdot))
        p0 = wps[k].pose.position
        h = times[k + 1] - times[k]
        data = np.array(
            [
                np.concatenate([p0, np.zeros(3)]),
                twists[k] * h,
                accels[k] * h * h,
                np.concatenate([p0 + steps[k][:3], delta]),
                np.concatenate([twists[k + 1][:3], theta_dot1]) * h,
                np.concatenate([accels[k + 1][:3], theta_ddot1]) * h * h,
            ]
        )
        coefficients = (core._HERMITE @ data) / (h ** np.arange(6.0))[:, None]
        rate = core._DERIVATIVE @ coefficients
        tables.append(np.hstack([coefficients, rate, core._DERIVATIVE @ rate]))
    return twists, accels, np.array(tables)


@pytest.mark.parametrize("seed", range(40))
def test_the_vectorised_build_equals_the_segment_by_segment_one(seed: int) -> None:
    """Random trajectories (2-40 waypoints, some interior and first twists and accels
    given): the knot rates and every segment table to 1e-12 of their scale."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 41))
    times = np.cumsum(rng.uniform(0.1, 1.0, n))
    quaternion = rng.normal(size=4)
    wps = []
    for k in range(n):
        quaternion = quaternion / np.linalg.norm(quaternion)
        interior = 0 < k < n - 1 or (k == 0 and seed % 2 == 0)
        twist = 0.5 * rng.normal(size=6) if interior and rng.random() < 0.3 else None
        accel = 0.5 * rng.normal(size=6) if interior and rng.random() < 0.3 else None
        wps.append(Waypoint(times[k], Pose(rng.uniform(-1, 1, 3), quaternion), twist, accel))
        quaternion = quaternion + 0.3 * rng.normal(size=4)
    tr = Trajectory(wps)
    twists, accels, tables = reference_build(wps)
    for mine, theirs in (
        (np.array([tr.knot(k).twist for k in range(n)]), twists),
        (np.array([tr.knot(k).accel for k in range(n)]), accels),
        (np.array(tr.curve._tables), tables),
    ):
        scale = max(float(np.max(np.abs(theirs))), 1.0)
        np.testing.assert_allclose(mine, theirs, rtol=0.0, atol=1e-12 * scale)


def test_quats_to_rotvecs_is_quat4_to_rotvec_row_by_row() -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(size=(200, 4))
    q[:50, 1:] *= 1e-6  # around the small-angle switch
    q[50:60, 0] = 0.0  # half a turn
    q /= np.linalg.norm(q, axis=1)[:, None]
    expected = np.array([quat4_to_rotvec(*row) for row in q.tolist()])
    np.testing.assert_allclose(quats_to_rotvecs(q), expected, rtol=1e-14, atol=1e-15)


# -- validation against limits, cable lengths and the wrench set --------------------------


def line(
    robot: Robot, times: list[float], xs: list[float], rotvecs: list | None = None, stop=False
) -> Trajectory:
    """Along x from home; with stop=True the robot rests at every waypoint, so each
    segment is a separate rest-to-rest move and its peaks stay in it."""
    rotvecs = rotvecs or [(0.0, 0.0, 0.0)] * len(times)
    rest = ZERO6 if stop else None
    return Trajectory(
        [
            Waypoint(
                t, Pose.from_rotvec(robot.home.position + np.array([x, 0.0, 0.0]), rv), rest, rest
            )
            for t, x, rv in zip(times, xs, rotvecs, strict=True)
        ]
    )


def rejected_by_validate(tr: Trajectory, robot: Robot, limits=LIMITS, **kw) -> TrajectoryError:
    with pytest.raises(TrajectoryError) as info:
        validate(tr, robot, limits, **kw)
    return info.value


def test_a_gentle_trajectory_passes(reference8: Robot) -> None:
    tr = line(reference8, [0.0, 2.0, 4.0, 6.0], [0.0, 0.2, -0.1, 0.0])
    calls = []

    def in_w(pose: Pose, twist: np.ndarray, accel: np.ndarray) -> None:
        assert isinstance(pose, Pose) and twist.shape == accel.shape == (6,)
        calls.append(pose)

    assert validate(tr, reference8, LIMITS, in_w) is None
    assert len(calls) >= 600  # every 10 ms over 6 s


def test_speed_limit_names_the_segment(reference8: Robot) -> None:
    # slow, slow, then 0.5 m in 0.5 s in the segment that starts at waypoint 3
    tr = line(reference8, [0.0, 2.0, 4.0, 6.0, 6.5, 9.0], [0.0, 0.02, 0.04, 0.06, 0.56, 0.56])
    err = rejected_by_validate(tr, reference8)
    assert (err.waypoint, err.limit) == (3, "linear_speed")
    assert err.value > LIMITS.linear_speed and f"{err.value:.6g} m/s" in str(err)
    assert str(err).startswith("waypoint 3: linear_speed:") and "at t=6." in str(err)


def test_the_first_segments_alone_are_checked_where_they_lie(reference8: Robot) -> None:
    """`segments`: a transition's first segment, checked in place although it ends
    moving (a free interior velocity); what lies beyond is not judged, what lies within
    is, naming its waypoint."""
    tr = line(reference8, [0.0, 2.0, 4.0, 6.0, 6.5, 9.0], [0.0, 0.02, 0.04, 0.06, 0.56, 0.56])
    assert np.any(tr.knot(1).twist)
    checked: list[float] = []

    def record(pose: Pose, twist: np.ndarray, accel: np.ndarray) -> None:
        checked.append(pose.position[0])  # a wrench check with no batch screen: every sample

    times = list(validation_steps(tr, reference8, LIMITS, record, segments=1))
    assert times[0] == 0.0 and times[-1] == 2.0
    assert len(checked) == 201  # every 10 ms
    assert list(validation_steps(tr, reference8, LIMITS, segments=3))[-1] == 6.0
    with pytest.raises(TrajectoryError) as info:
        list(validation_steps(tr, reference8, LIMITS, segments=4))
    assert (info.value.waypoint, info.value.limit) == (3, "linear_speed")


def test_accel_limit(reference8: Robot) -> None:
    # 0.3 m in 1 s from rest to rest: peak 10/sqrt(3) * 0.3 = 1.73 m/s² in segment 1
    tr = line(reference8, [0.0, 2.0, 3.0, 5.0], [0.0, 0.02, 0.32, 0.32], stop=True)
    err = rejected_by_validate(tr, reference8, TrajectoryLimits(linear_accel=1.5))
    assert (err.waypoint, err.limit) == (1, "linear_accel")
    assert 1.5 < err.value <= 10 / math.sqrt(3) * 0.3 + 1e-12


def test_angular_limits(reference8: Robot) -> None:
    # 0.6 rad in 2 s from rest: peaks 15/8 * 0.3 = 0.5625 rad/s, 10/sqrt(3) * 0.15 rad/s²
    rotvecs = [(0, 0, 0), (0, 0, 0), (0, 0, 0.6), (0, 0, 0.6)]
    tr = line(reference8, [0.0, 1.0, 3.0, 4.0], [0.0] * 4, rotvecs, stop=True)
    err = rejected_by_validate(tr, reference8, TrajectoryLimits(angular_speed=0.5))
    assert (err.waypoint, err.limit) == (1, "angular_speed")
    assert 0.5 < err.value <= 0.5625 + 1e-12 and "rad/s exceeds" in str(err)
    err = rejected_by_validate(tr, reference8, TrajectoryLimits(angular_accel=0.8))
    assert (err.waypoint, err.limit) == (1, "angular_accel")
    assert 0.8 < err.value <= 10 / math.sqrt(3) * 0.15 + 1e-12


def test_cable_length_limit_names_the_cable(reference8: Robot) -> None:
    # a pure translation: lengths are convex along the line, so only cables out of range
    # at the far end can fail, and at that pose exactly one is (cable 1, too long)
    far = reference8.home.position + np.array([-1.45, -1.45, 1.05])
    lengths = reference8.cable_lengths(Pose(far))
    assert np.flatnonzero(lengths > 4.2).tolist() == [1]
    tr = Trajectory([Waypoint(0.0, reference8.home), Waypoint(8.0, Pose(far))])
    err = rejected_by_validate(tr, reference8)
    assert (err.waypoint, err.limit) == (0, "cable_length")
    assert 4.2 < err.value < lengths[1] and "cable 1 length" in str(err)
    assert "[0.3, 4.2] m" in str(err)


def test_wrench_check_reason_is_reported(reference8: Robot) -> None:
    tr = line(reference8, [0.0, 2.0, 4.0, 6.0], [0.0, 0.1, 0.2, 0.3])

    def beyond(pose: Pose, twist: np.ndarray, accel: np.ndarray) -> str | None:
        if pose.position[0] > 0.15:
            return "cable 3 tension below t_min"
        return None

    err = rejected_by_validate(tr, reference8, wrench_check=beyond)
    assert (err.waypoint, err.limit, err.value) == (1, "wrench_set", None)
    assert "cable 3 tension below t_min" in str(err)


def test_every_waypoint_time_is_checked(reference8: Robot) -> None:
    """A waypoint between two sample instants is still checked, at its exact pose."""
    tr = line(reference8, [0.0, 1.2345, 2.5], [0.0, 0.1, 0.0])
    target = tr.waypoints[1].pose

    def only_at_the_waypoint(pose: Pose, twist: np.ndarray, accel: np.ndarray) -> str | None:
        return "singular" if np.abs(liediff(pose, target)).max() < 1e-12 else None

    err = rejected_by_validate(tr, reference8, wrench_check=only_at_the_waypoint)
    assert (err.waypoint, err.limit) == (1, "wrench_set") and "t=1.2345 s" in str(err)


def test_validate_counts_waypoints_and_duration(reference8: Robot) -> None:
    tr = line(reference8, [0.0, 10.0, 20.0], [0.0, 0.1, 0.0])
    assert rejected_by_validate(tr, reference8, TrajectoryLimits(max_waypoints=2)).limit == (
        "max_waypoints"
    )
    err = rejected_by_validate(tr, reference8, TrajectoryLimits(max_duration=15.0))
    assert (err.limit, err.value) == ("max_duration", 20.0)


def test_max_waypoints_cannot_be_raised_past_what_the_loop_survives() -> None:
    """Some work on the daemon's loop still grows with the number of waypoints (see
    MAX_WAYPOINTS): a config may lower the limit, not raise it."""
    from pydantic import ValidationError

    assert TrajectoryLimits().max_waypoints == MAX_WAYPOINTS == 10_000
    assert TrajectoryLimits(max_waypoints=500).max_waypoints == 500
    with pytest.raises(ValidationError, match="max_waypoints") as info:
        TrajectoryLimits.model_validate({"max_waypoints": 10_001})
    assert "less than or equal to 10000" in str(info.value)


def test_limits_are_a_strict_config_section() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="linear_sped"):
        TrajectoryLimits.model_validate({"linear_sped": 1.0})
    with pytest.raises(ValidationError, match="linear_speed"):
        TrajectoryLimits.model_validate({"linear_speed": -1.0})
    assert TrajectoryLimits.model_validate({"linear_speed": 0.5}).angular_speed == 2.0


# -- transitions --------------------------------------------------------------------------


def moving_state(seed: int, speed: float = 0.5) -> Reference:
    rng = np.random.default_rng(seed)
    twist = rng.normal(size=6)
    twist[:3] *= speed / np.linalg.norm(twist[:3])
    twist[3:] *= speed / np.linalg.norm(twist[3:])
    pose = Pose.from_rotvec(HOME + rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.2, 0.2, 3))
    return Reference(pose, twist, rng.uniform(-1.5, 1.5, 6))


def planned(seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    return Trajectory(
        [
            Waypoint(
                t, Pose.from_rotvec(HOME + rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.2, 0.2, 3))
            )
            for t in (0.0, 1.5, 3.0, 4.5)
        ]
    )


@settings(max_examples=15)
@given(st.integers(0, 10**6), st.floats(0.0, 0.9))
def test_approach_from_a_moving_reference_is_c2_and_within_limits(seed: int, speed: float) -> None:
    current = moving_state(seed, speed)
    target = planned(seed + 1)
    tr = approach(current, target, LIMITS, start=10.0)
    assert tr.start_time == 10.0
    assert_same_state(tr.sample(10.0), current, 1e-12)  # starts exactly where we are
    assert_same_state(tr.sample(math.nextafter(10.0, 20.0)), current, 1e-9)
    # the joint into the trajectory: the same state from the left and the right
    joint = tr.waypoints[1].t
    assert_same_state(tr.sample(math.nextafter(joint, 0.0)), tr.sample(joint), 1e-9)
    # then the trajectory itself, unchanged, shifted
    offset = joint - target.start_time
    for t in inner_times(target, 10):
        assert_same_state(tr.sample(t + offset), target.sample(t), 1e-9)
    assert_within(peak_rates(tr), LIMITS)


@settings(max_examples=15)
@given(st.integers(0, 10**6), st.floats(0.05, 0.9), st.floats(-1.0, 1.0))
def test_a_stop_comes_to_rest_within_limits_without_turning_back(
    seed: int, speed: float, push: float
) -> None:
    """stop_steps from a moving reference (accelerating along its motion, push > 0, or
    braking, push < 0): C2 at its start, at rest at its end, within the rate limits, and
    the speed along the current direction never reverses (a fixed rest pose at the
    constant-deceleration distance made the shortest quintic overshoot it and return)."""
    moving = moving_state(seed, speed)
    accel = np.concatenate([moving.twist[:3], moving.twist[3:]]) * push * 2.0
    current = moving._replace(accel=accel)
    tr = run_steps(stop_steps(current, LIMITS, start=3.0))
    assert_same_state(tr.sample(3.0), current, 1e-12)
    end = tr.sample(tr.end_time)
    assert not end.twist.any() and not end.accel.any()
    assert_within(peak_rates(tr), LIMITS)
    times = np.linspace(tr.start_time, tr.end_time, 400)
    along = [tr.sample(t).twist[:3] @ current.twist[:3] for t in times]
    assert min(along) >= -1e-9 * speed**2
    # and it stops promptly: the cubic velocity profile at the limit takes 1.5 speed / accel
    prompt = 1.5 * max(speed / LIMITS.linear_accel, speed / LIMITS.angular_accel)
    assert tr.end_time - 3.0 <= 2.0 * prompt + 0.05


def test_approach_result_passes_validation(reference8: Robot) -> None:
    tr = approach(moving_state(3, 0.8), planned(4), LIMITS)
    validate(tr, reference8, LIMITS)
    assert tr.end_time == planned(4).end_time  # default: the trajectory keeps its times


def test_approach_adds_nothing_when_already_at_the_start() -> None:
    target = planned(5)
    here = target.sample(target.start_time)
    assert approach(here, target, LIMITS) is target
    moved = approach(here, target, LIMITS, start=7.0)
    assert moved.start_time == 7.0 and len(moved.waypoints) == len(target.waypoints)


def test_approach_from_beyond_the_limits_is_rejected() -> None:
    current = moving_state(6)._replace(twist=np.array([1.5, 0.0, 0.0, 0.0, 0.0, 0.0]))
    with pytest.raises(TrajectoryError) as info:
        approach(current, planned(7), LIMITS)
    assert (info.value.limit, info.value.value) == ("linear_speed", 1.5)
    assert "current reference" in str(info.value)


def test_approach_that_no_duration_allows_is_rejected() -> None:
    # accelerating at the limit, so near the speed limit that even the shortest ramp of
    # its acceleration (1 ms) ends above it: any blend either brakes too hard or runs
    # too fast
    current = moving_state(8, 0.99)._replace(accel=np.array([4.99, 0, 0, 0, 0, 0.0]))
    current = current._replace(twist=np.array([0.999, 0, 0, 0, 0, 0.0]))
    with pytest.raises(TrajectoryError) as info:
        approach(current, planned(9), TrajectoryLimits(max_duration=30.0))
    assert info.value.limit in {"linear_speed", "linear_accel"}
    assert "no transition" in str(info.value)


def long_line(n: int) -> Trajectory:
    """n waypoints 10 ms apart on a slow line from home (a long planner's message)."""
    step = np.array([1e-4, 0.0, 0.0])
    return Trajectory([Waypoint(0.01 * k, Pose(HOME + k * step)) for k in range(n)])


def test_each_approach_step_does_work_independent_of_the_length(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A service plans a trajectory's approach between control cycles, one step at a
    time (Service._in_slack), and shifts the trajectory in the first: the waypoint
    objects each step makes must not grow with the trajectory's length.  (Copying
    10,000 waypoints in one step stalled the loop for 200 ms and braked the robot.)"""
    made = [0]
    post_init = Waypoint.__post_init__

    def counting(self: Waypoint) -> None:
        made[0] += 1
        post_init(self)

    monkeypatch.setattr(Waypoint, "__post_init__", counting)
    current = moving_state(11, 0.3)
    most = {}
    for n in (10, 3000):
        target = long_line(n)

        def plan(target: Trajectory = target) -> Generator[None, None, Trajectory]:
            shifted = target.shifted(20.0)  # the service's plan, as in submit_trajectory
            return (yield from approach_steps(current, shifted, LIMITS))

        steps, counts = plan(), []
        while True:
            made[0] = 0
            try:
                next(steps)
            except StopIteration as done:
                planned = done.value
                counts.append(made[0])
                break
            counts.append(made[0])
        assert len(counts) > 3 and planned.start_time < 20.0  # it did blend in
        most[n] = max(counts)
    assert most[10] == most[3000] <= 2  # the leads: the current state, placed
    made[0] = 0
    head = Trajectory([planned.knot(0), planned.knot(1)])  # what the service validates
    assert made[0] <= 2 and len(head) == 2


def test_shifted_and_blended_trajectories_keep_their_waypoints_and_knots() -> None:
    target = Trajectory(with_interior_twists(random_waypoints(21), 22))
    moved = target.shifted(3.5).shifted(-1.25)
    current = moving_state(23, 0.4)
    tr = approach(current, moved, LIMITS, start=40.0)
    offset = tr.waypoints[1].t - target.start_time
    assert len(tr) == len(tr.waypoints) == len(tr.knots) == len(target) + 1
    assert (tr.start_time, tr.waypoints[0].pose) == (40.0, current.pose)
    assert tr.end_time == pytest.approx(target.end_time + offset, abs=1e-12)
    assert tr.duration == pytest.approx(tr.end_time - 40.0, abs=1e-12)
    for w, original in zip(tr.waypoints[1:], target.waypoints, strict=True):
        assert w.t == pytest.approx(original.t + offset, abs=1e-12) and w.pose is original.pose
    for k, knot in enumerate(tr.knots):
        assert (knot.t, knot.pose) == (tr.waypoints[k].t, tr.waypoints[k].pose)
        assert_same_state(tr.sample(knot.t), Reference(knot.pose, knot.twist, knot.accel), 1e-9)
        assert tr.waypoint_index(knot.t) == k
        assert tr.waypoint_index(math.nextafter(knot.t, -math.inf)) == max(k - 1, 0)
    assert_same_state(tr.sample(40.0), current, 1e-12)
    later = tr.shifted(7.0)  # the blend moves with the rest
    assert later.start_time == 47.0 and len(later) == len(tr)
    for t in inner_times(tr, 20):
        assert_same_state(later.sample(t + 7.0), tr.sample(t), 1e-9)
        assert later.waypoint_index(t + 7.0) == tr.waypoint_index(t)
    with pytest.raises(IndexError, match="knot 7 of a trajectory of 7 waypoints"):
        tr.knot(len(tr))
    with pytest.raises(ValueError, match="begins with a blend already"):
        tr.after_blend([tr.knot(0)], 1.0)


def at_rest(pose: Pose) -> Reference:
    return Reference(pose, ZERO6, ZERO6)


def assert_arrives_at_rest(tr: Trajectory, target: Pose) -> None:
    end = tr.sample(tr.end_time)
    assert np.abs(liediff(end.pose, target)).max() < 1e-12
    assert_same_state(tr.sample(math.nextafter(tr.end_time, 0.0)), at_rest(target), 1e-9)


@pytest.mark.parametrize(
    ("dp", "rotvec", "binding"),
    [
        ((0.8, -0.3, 0.2), (0.0, 0.0, 0.0), "linear_speed"),
        ((0.05, 0.0, 0.0), (0.0, 0.0, 0.0), "linear_accel"),
        ((0.0, 0.0, 0.0), (0.0, 0.5, 2.5), "angular_speed"),
        ((0.0, 0.0, 0.01), (0.25, 0.0, 0.0), "angular_accel"),
    ],
)
def test_goto_from_rest_is_time_optimal_minimum_jerk(dp, rotvec, binding: str) -> None:
    start = Pose.from_rotvec(HOME, (0.1, 0.0, 0.0))
    target = Pose.from_rotvec(HOME + np.array(dp), rotvec)
    tr = goto(at_rest(start), target, LIMITS, start=3.0)
    assert tr.start_time == 3.0
    assert_arrives_at_rest(tr, target)
    peaks = peak_rates(tr, 20001)
    assert_within(peaks, LIMITS)
    assert peaks[binding] > 0.999 * getattr(LIMITS, binding)
    # along the straight line and the geodesic: every pose lies on them
    step = liediff(start, target)
    for t in inner_times(tr, 9):
        d = liediff(start, tr.sample(t).pose)
        assert np.linalg.norm(np.cross(d[:3], step[:3])) < 1e-12
        assert np.linalg.norm(np.cross(d[3:], step[3:])) < 1e-12


@settings(max_examples=15)
@given(st.integers(0, 10**6), st.floats(0.0, 0.9))
def test_goto_from_a_moving_state(seed: int, speed: float) -> None:
    current = moving_state(seed, speed)
    target = Pose.from_rotvec(HOME + np.array([0.1, -0.2, 0.05]), (0.3, 0.0, -0.2))
    tr = goto(current, target, LIMITS, start=1.0)
    assert_same_state(tr.sample(1.0), current, 1e-12)
    assert_same_state(tr.sample(math.nextafter(1.0, 2.0)), current, 1e-9)
    assert_arrives_at_rest(tr, target)
    assert_within(peak_rates(tr), LIMITS)


JERK_LIMITS = TrajectoryLimits(linear_jerk=50.0, angular_jerk=100.0)  # as the configs ship


def states_along_a_double_s_goto(n: int = 60) -> list[Reference]:
    """n reference states along a jerk-limited goto from rest (0.3 m and 0.4 rad): the
    first phase accelerates at the limit toward the speed a hold or a new goto must not
    pass."""
    start = Pose.from_rotvec(HOME - np.array([0.15, 0.0, 0.075]), (0.0, 0.0, -0.2))
    end = Pose.from_rotvec(HOME + np.array([0.15, 0.0, 0.075]), (0.0, 0.0, 0.2))
    flight = goto(at_rest(start), end, JERK_LIMITS)
    return [flight.sample(t) for t in np.linspace(0.0, flight.end_time, n + 2)[1:-1]]


def assert_a_jerk_limited_transition(tr: Trajectory, current: Reference, start: float) -> None:
    """`tr` starts exactly in `current`, C2, and keeps the rate and jerk limits."""
    assert tr.start_time == start
    assert_same_state(tr.sample(start), current, 1e-12)
    assert_same_state(tr.sample(math.nextafter(start, math.inf)), current, 1e-9)
    assert_within(peak_rates(tr), JERK_LIMITS)
    assert jerk_excess(tr, JERK_LIMITS.linear_jerk, JERK_LIMITS.angular_jerk) <= 1.0


def test_holds_gotos_and_approaches_from_anywhere_in_a_jerk_limited_goto() -> None:
    """With the jerk bounded, a state accelerating hard leaves one quintic segment to
    rest no duration at all (shorter ones break the jerk limit, longer ones carry the
    acceleration past the speed limit): a hold or a new goto sent during a goto's first
    phase was refused ("no transition of up to 3600 s", 17 % of such states).  The
    acceleration is first ramped to zero at the jerk limit; every state plans, each
    transition within the limits."""
    home = Pose(HOME)
    body = planned(11)
    ramped = np.zeros(3, int)
    for k, current in enumerate(states_along_a_double_s_goto()):
        hold = run_steps(stop_steps(current, JERK_LIMITS, start=2.0))
        assert_a_jerk_limited_transition(hold, current, 2.0)
        end = hold.sample(hold.end_time)
        assert not end.twist.any() and not end.accel.any()
        times = np.linspace(hold.start_time, hold.end_time, 200)
        along = [hold.sample(t).twist[:3] @ current.twist[:3] for t in times]
        if current.twist[:3] @ current.accel[:3] >= 0.0:  # (braking hard, it may: stop_steps)
            assert min(along) >= 0.0, k  # never turning back
        back = goto(current, home, JERK_LIMITS, start=2.0)
        assert_a_jerk_limited_transition(back, current, 2.0)
        assert_arrives_at_rest(back, home)
        into = approach(current, body, JERK_LIMITS, start=2.0)
        assert_a_jerk_limited_transition(into, current, 2.0)
        joint = into.knot(len(into) - len(body)).t
        assert_same_state(into.sample(joint + 0.05), body.sample(body.start_time + 0.05), 1e-9)
        ramped += np.array([len(hold), len(back), len(into) - len(body) + 1]) > 2
    print("ramped (hold, goto, approach):", ramped)
    assert ramped.min() >= 5  # every kind from states of the first phase


def test_without_the_ramp_those_states_had_no_transition(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_ramp(current: Reference, limits: TrajectoryLimits) -> list[Waypoint]:
        raise TrajectoryError("ramp", "no ramp")

    monkeypatch.setattr(transitions, "_ramps", no_ramp)
    refused = 0
    for current in states_along_a_double_s_goto():
        try:
            run_steps(stop_steps(current, JERK_LIMITS))
        except TrajectoryError as exc:
            assert "no transition of up to 3600 s" in str(exc)
            refused += 1
    assert refused >= 5


def test_goto_nowhere_and_tiny_moves() -> None:
    here = Pose.from_rotvec(HOME, (0.1, 0.2, 0.3))
    tr = goto(at_rest(here), here, LIMITS)
    assert tr.duration == pytest.approx(MIN_BLEND)
    for t in np.linspace(-1.0, 1.0, 21):
        ref = tr.sample(t)
        assert ref.pose == here and not ref.twist.any() and not ref.accel.any()
    for size in (1e-15, 1e-9, 1e-6):
        target = Pose.from_rotvec(HOME + size, (0.1, 0.2, 0.3 + size))
        tiny = goto(at_rest(here), target, LIMITS)
        assert_arrives_at_rest(tiny, target)
        assert np.isfinite(tiny.duration) and tiny.duration >= MIN_BLEND
        assert_within(peak_rates(tiny, 101), LIMITS)


@pytest.mark.parametrize("angle", [math.pi - 1e-6, math.pi])
def test_goto_half_a_turn(angle: float) -> None:
    axis = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    here = Pose(HOME)
    target = Pose.from_rotvec(HOME, angle * axis)
    tr = goto(at_rest(here), target, LIMITS)
    assert_arrives_at_rest(tr, target)
    assert tr.duration == pytest.approx(15 / 8 * angle / LIMITS.angular_speed, rel=1e-6)
    for t in inner_times(tr, 10):
        ref = tr.sample(t)
        # a rotation about the fixed axis: ω is along it (either way round at exactly pi)
        assert np.linalg.norm(np.cross(ref.twist[3:], axis)) < 1e-9
        np.testing.assert_allclose(ref.twist, fd_twist(tr, t), atol=1e-6)
        np.testing.assert_allclose(ref.accel, fd_accel(tr, t), atol=1e-4)


@pytest.mark.parametrize("leads", [1, 2])
def test_a_packed_curve_samples_as_the_trajectory_it_came_from(leads: int) -> None:
    """The real-time core samples a curve unpacked from one array (no rebuilding): the
    same reference as the trajectory, blend and time shift included, at every time (a
    blend of one segment, or of two: a ramp's end between)."""
    body = Trajectory(random_waypoints(7, n=9))
    first = Waypoint(
        body.start_time - 0.8,
        Pose.from_rotvec([0.1, -0.2, 1.1], [0.0, 0.1, 0.0]),
        np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.02]),
        np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0]),
    )
    ramped = Waypoint(
        body.start_time - 0.5,
        Pose.from_rotvec([0.12, -0.2, 1.1], [0.0, 0.1, 0.01]),
        np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.02]),
        np.zeros(6),
    )
    blended = body.after_blend([first, ramped][:leads], 0.3).shifted(12.5)
    assert blended.lead_segments == leads and len(blended) == 9 + leads
    header, data = blended.curve.packed()
    copy = Curve.unpacked(header, data.copy())
    times = np.linspace(blended.start_time - 1.0, blended.end_time + 1.0, 500)
    for t in [*times, *(w.t for w in blended.waypoints)]:
        assert copy.sample(float(t)).same_as(blended.sample(float(t))), t
    assert (copy.start_time, copy.end_time) == (blended.start_time, blended.end_time)
    with pytest.raises(ValueError, match="9 knots cannot hold"):
        Curve.unpacked(header, data[:-1])


def test_a_waypoint_never_shares_a_vector_someone_can_change() -> None:
    """A waypoint copies and freezes a twist or accel given as a list or a writable array
    (a change to the caller's array does not reach it); one that nothing can change (a
    row of a read-only array, as the path timing hands over) it keeps as given."""
    pose = Pose((0.0, 0.0, 1.0))
    mine = np.ones(6)
    w = Waypoint(0.0, pose, mine, [0.0] * 6)
    mine[0] = 5.0
    assert w.twist[0] == 1.0 and not w.twist.flags.writeable
    assert not w.accel.flags.writeable
    base = np.ones((2, 6))
    view = base[0]
    view.flags.writeable = False  # the base stays writable: still copied
    assert Waypoint(0.0, pose, view).twist is not view
    base.flags.writeable = False
    shared = base[1]
    assert Waypoint(0.0, pose, shared).twist is shared
