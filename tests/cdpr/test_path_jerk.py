"""Jerk-limited path timing: the averaged time law (cdpr.path.time_law) held to scipy's
quadrature and to finite differences; the standard paths timed under jerk limits keep
them, pass the daemon's validation and an independent LP, and take only a little longer."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from cdpr.path import Path, PathPoint, timing
from cdpr.path.time_law import AveragedLaw, TimeLaw
from cdpr.path.timing import Timing, time_path
from cdpr.trajectory.jerk import segment_jerks
from daemon.service.planner import validate_as_the_daemon
from tests.cdpr.test_path import lp_feasible, samples
from tests.daemon_stack import config_for
from tuning.scenarios import STANDARD_SET

WIDTH = 0.2


def bang_bang() -> TimeLaw:
    """s = t² to 0.25 at t = 0.5 (s' = 1), then braking at 2 to rest at 0.5, t = 1."""
    return TimeLaw(
        np.array([0.0, 0.25, 0.5]), np.array([0.0, 1.0, 0.0]), np.array([2.0, -2.0]),
        np.array([0.0, 0.5, 1.0]),
    )  # fmt: skip


def test_the_time_law_and_its_integral_against_quadrature() -> None:
    law = bang_bang()
    for t in (-0.3, 0.0, 0.2, 0.5, 0.77, 1.0, 1.4):
        S, s, v = law.at(np.array([t]))
        expected_s = t * t if 0 <= t <= 0.5 else 0.5 - (1 - t) ** 2 if 0.5 < t <= 1 else 0.5
        assert s[0] == pytest.approx(0.0 if t < 0 else expected_s, abs=1e-15)
        inside = [p for p in (0.5, 1.0) if p < t]
        integral = quad(lambda x: law.at(np.array([x]))[1][0], 0.0, max(t, 0.0), points=inside)
        assert S[0] == pytest.approx(integral[0], abs=1e-12)
        h = 1e-6
        rate = (law.at(np.array([t + h]))[1] - law.at(np.array([t - h]))[1]) / (2 * h)
        if t not in (0.0, 0.5, 1.0):
            assert v[0] == pytest.approx(rate[0], abs=1e-6)


def test_the_average_is_the_window_s_mean_with_its_rates_and_bounded_jerk() -> None:
    law = bang_bang()
    averaged = AveragedLaw(law, WIDTH)
    assert averaged.end == pytest.approx(1.0 + WIDTH)
    times = np.linspace(0.0, averaged.end, 241)
    s, rate, accel = averaged.at(times)
    for t, value in zip(times[::20], s[::20], strict=True):
        mean = quad(lambda x: law.at(np.array([x]))[1][0], t - WIDTH, t, limit=200)[0] / WIDTH
        assert value == pytest.approx(mean, abs=1e-10)
    h = 1e-6
    up, down = averaged.at(times + h), averaged.at(times - h)
    np.testing.assert_allclose(rate, (up[0] - down[0]) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(accel, (up[1] - down[1]) / (2 * h), atol=1e-5)
    jerk = (up[2] - down[2]) / (2 * h)
    assert np.abs(jerk).max() <= 4.0 / WIDTH * (1 + 1e-6)  # s'' swings from 2 to -2
    # at rest with no acceleration at both ends, and never beyond the law's extremes
    ends = averaged.at(np.array([0.0, averaged.end]))
    np.testing.assert_allclose([e.tolist() for e in ends], [[0.0, 0.5], [0, 0], [0, 0]], atol=1e-12)
    assert rate.max() <= 1.0 + 1e-12 and np.abs(accel).max() <= 2.0 + 1e-12


def test_each_path_point_s_time_on_the_average_reaches_it() -> None:
    averaged = AveragedLaw(bang_bang(), WIDTH)
    points = np.concatenate([np.linspace(0.0, 0.05, 9), np.linspace(0.06, 0.5, 30)])
    times = averaged.timed_at(points)
    assert times[0] == 0.0 and times[-1] == averaged.end
    np.testing.assert_allclose(averaged.at(times)[0], points, atol=1e-12)
    assert np.all(np.diff(times) > 0.0)


def test_on_a_long_path_each_point_s_time_reaches_it_to_rounding() -> None:
    """200 m in 20,000 intervals, a 2,000-line part's size: the integral of s from 0
    grows to ~10^4 m s, whose rounding stalled Newton's method on the difference of two
    such integrals; each point's time puts the window's mean on the point (scipy's
    quadrature over the window, at every 500th point)."""
    rng = np.random.default_rng(3)
    n, width = 20_000, 0.05
    grid = np.linspace(0.0, 200.0, n + 1)
    speeds = np.concatenate([[0.0], rng.uniform(0.2, 1.5, n - 1), [0.0]])
    dt = 2.0 * np.diff(grid) / (speeds[:-1] + speeds[1:])
    law = TimeLaw(grid, speeds, np.diff(speeds) / dt, np.concatenate([[0.0], np.cumsum(dt)]))
    averaged = AveragedLaw(law, width)
    times = averaged.timed_at(grid)
    assert times[0] == 0.0 and times[-1] == averaged.end and np.all(np.diff(times) > 0.0)
    for k in range(500, n, 500):
        t = times[k]
        inside = law.t[(law.t > t - width) & (law.t < t)]
        mean = quad(lambda x: law.at(np.array([x]))[1][0], t - width, t, points=inside)[0]
        assert mean / width == pytest.approx(grid[k], abs=1e-9), k


@pytest.fixture(scope="module")
def cia402():
    return config_for("cia402")


@pytest.mark.parametrize(
    ("name", "longer"), [("figure_eight", 2.5), ("vertical_lift", 1.1), ("edge_move", 1.1)]
)
def test_the_standard_paths_timed_under_jerk_limits_keep_them(
    cia402, name: str, longer: float
) -> None:
    """Timed with the jerk bounded, each standard path's trajectory keeps the bounds,
    passes the daemon's validation (its own limits) and an independent LP at its samples.
    TOPP-RA alone gives hundreds of m/s³ where its path acceleration switches, and on the
    figure-eight (174 poses with 5 cm blends: the bends change over millimetres) 10^5
    m/s³; bounded, the lines take at most 10 % longer, the figure-eight 2.2x (what its
    bends allow at 50 m/s³)."""
    robot = cia402.robot
    poses = [w.pose for w in STANDARD_SET[name](robot).waypoints]
    blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
    path = Path(tuple(PathPoint(p, blend=b) for p, b in zip(poses, blends, strict=True)))
    unbounded = {"linear_jerk": None, "angular_jerk": None}
    free = time_path(path, robot, cia402.trajectory.model_copy(update=unbounded), Timing(5.0))
    limits = cia402.trajectory.model_copy(update={"linear_jerk": 50.0, "angular_jerk": 100.0})
    bound = time_path(path, robot, limits, Timing(margin=5.0))
    linear, angular = segment_jerks(*bound.curve.segments()[1:])
    assert linear.max() <= 50.0 and angular.max() <= 100.0
    loose = segment_jerks(*free.curve.segments()[1:])
    assert loose[0].max() > 50.0  # the bound did something
    validate_as_the_daemon(bound, cia402)
    for w in samples(bound, 200):
        assert lp_feasible(robot, w, margin=4.0), f"t={w.t:.3f}: no tensions"
    assert free.duration < bound.duration <= longer * free.duration


@pytest.mark.parametrize(
    ("name", "linear_jerk", "angular_jerk", "within"),
    [("vertical_lift", 50.0, 100.0, 1e-6), ("figure_eight", 50.0, 1e9, 1e-6),
     ("edge_move", 1e9, 10.0, 1e-6), ("figure_eight", 1e9, 10.0, 1e-5)],
    ids=["lift", "figure_eight_linear", "edge_move_angular", "figure_eight_angular"],
)  # fmt: skip
def test_the_window_search_s_jerk_estimate_is_the_trajectory_s_jerk(
    cia402, name: str, linear_jerk: float, angular_jerk: float, within: float,
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """The averaging windows are compared by a jerk estimated from the knots (no
    trajectory built); on every window tried it is the jerk segment_jerks measures on
    the trajectory those knots make: to rounding the linear one and the angular one
    about one axis (the edge move's turn), the figure-eight's to 2e-6 (the left
    Jacobian's terms the estimate leaves out).  A limit of 1e9 leaves the other one
    measured alone."""
    robot = cia402.robot
    poses = [w.pose for w in STANDARD_SET[name](robot).waypoints]
    blends = [0.0] + [0.05] * (len(poses) - 2) + [0.0]
    path = Path(tuple(PathPoint(p, blend=b) for p, b in zip(poses, blends, strict=True)))
    jerks = {"linear_jerk": linear_jerk, "angular_jerk": angular_jerk}
    limits = cia402.trajectory.model_copy(update=jerks)
    windows = []
    estimate = timing._jerk_estimate

    def recorded(model, times, speed, u, limits):
        value = estimate(model, times, speed, u, limits)
        windows.append((value, timing._jerk_excess(timing._knots(model, times, speed, u), limits)))
        return value

    monkeypatch.setattr(timing, "_jerk_estimate", recorded)
    time_path(path, robot, limits, Timing(margin=5.0))
    assert len(windows) >= 3  # the search widens until two in a row are longer
    for value, exact in windows:
        assert value == pytest.approx(exact, rel=within)
