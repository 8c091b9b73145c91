"""The capacity margin against references we did not write: scipy's HiGHS LP decides
whether the wrench a pose needs lies in W, scipy's null_space gives the limiting facet's
normal, and the robot's own dynamics give the wrench at rest."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.linalg import null_space
from scipy.optimize import linprog

from cdpr import Pose, Robot
from cdpr.reference import cable_segments
from cdpr.so3 import quat_to_matrix
from cdpr.wrench_margin import WrenchMargin, facet_normals, rest_wrenches, wrench_length

SURE = 0.5  # N: verdicts are compared this far from the boundary (the LP's tolerance)


def _in_w(A: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """HiGHS: is there t in [lo, hi] with A t = w?"""
    result = linprog(
        np.zeros(A.shape[1]), A_eq=A, b_eq=w, bounds=list(zip(lo, hi, strict=True)), method="highs"
    )
    assert result.status in (0, 2), result.message
    return result.status == 0


def _random_poses(robot: Robot, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians and rest wrenches (with 0-8 kg payloads) of random poses across the frame,
    tilted up to 0.4 rad."""
    rng = np.random.default_rng(seed)
    anchors = robot.geometry.anchors
    jacobians, wrenches = [], []
    for _ in range(count):
        p = rng.uniform(anchors.min(axis=0) + 0.3, anchors.max(axis=0) - 0.3)
        axis = rng.normal(size=3)
        angle = rng.uniform(0.0, 0.4)
        q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)])
        R = quat_to_matrix(q)
        _, u, _, _ = cable_segments(robot, p[None], R)
        r = robot.geometry.attachments @ R.T
        jacobians.append(np.hstack([u[0], np.cross(r, u[0])]))
        wrenches.append(rest_wrenches(robot.platform, R[None], rng.uniform(0.0, 8.0))[0])
    return np.array(jacobians), np.array(wrenches)


@pytest.mark.slow  # over 5 s of the default run's 10 minutes
def test_the_verdict_agrees_with_an_independent_lp_on_random_poses(reference8: Robot) -> None:
    model = WrenchMargin(reference8.t_min, reference8.force_max, 0.4)
    jacobians, wrenches = _random_poses(reference8, 400, seed=3)
    margins = model.margins(jacobians, wrenches)
    scale = np.array([1, 1, 1, 1 / 0.4, 1 / 0.4, 1 / 0.4])
    compared = inside = 0
    for J, w, margin in zip(jacobians, wrenches, margins, strict=True):
        if abs(margin) <= SURE:
            continue
        compared += 1
        feasible = _in_w(J.T, w, reference8.t_min, reference8.force_max)
        inside += feasible
        assert feasible == (margin > 0.0), (margin, w)
        # a scaled LP gives the same verdict: the scale changes the margin, not W
        assert _in_w((J * scale).T, w * scale, reference8.t_min, reference8.force_max) == feasible
    assert compared >= 380
    assert 50 <= inside <= compared - 50  # both verdicts are exercised


def test_the_margin_is_the_distance_to_the_nearest_facet(reference8: Robot) -> None:
    """The ball of radius margin around w is in W (random directions, by the LP), and along
    the limiting facet's normal (scipy's null space of the other cables) W ends there."""
    length = wrench_length(reference8.geometry.attachments)
    model = WrenchMargin(reference8.t_min, reference8.force_max, length)
    scale = np.array([1, 1, 1, 1 / length, 1 / length, 1 / length])
    lo, hi = reference8.t_min, reference8.force_max
    jacobians, wrenches = _random_poses(reference8, 60, seed=4)
    checked = 0
    rng = np.random.default_rng(5)
    for J, w in zip(jacobians, wrenches, strict=True):
        margin = model.margin(J, w)
        if margin.value < 5.0:
            continue
        checked += 1
        A, ws = (J * scale).T, w * scale
        for e in rng.normal(size=(5, 6)):
            assert _in_w(A, ws + 0.99 * margin.value * e / np.linalg.norm(e), lo, hi)
        others = [j for j in range(reference8.n_cables) if j not in margin.at_limit]
        c = null_space(A[:, others].T)[:, 0]
        out = [not _in_w(A, ws + sign * 1.01 * margin.value * c, lo, hi) for sign in (1, -1)]
        within = [_in_w(A, ws + sign * 0.99 * margin.value * c, lo, hi) for sign in (1, -1)]
        assert any(out) and all(within)
        # the limiting cables sit at the bounds `upper` names at the facet's nearest point
        side = 1 if out[0] else -1
        t = linprog(
            np.zeros(8),
            A_eq=A,
            b_eq=ws + side * margin.value * c,
            bounds=list(zip(lo, hi, strict=True)),
        ).x
        for j, up in zip(margin.at_limit, margin.upper, strict=True):
            assert t[j] == pytest.approx(hi[j] if up else lo[j], abs=1e-3 * hi[j])
    assert checked >= 20


@pytest.mark.parametrize("cables, dof", [(6, 6), (7, 6), (10, 6), (4, 3)])
def test_other_robots_agree_with_the_lp_too(cables: int, dof: int) -> None:
    """Suspended (n = m), one and four redundant cables, and a planar robot."""
    rng = np.random.default_rng(cables)
    model = WrenchMargin(np.full(cables, 1.0), np.full(cables, 4.0), 1.0, dof=dof)
    jacobians = rng.normal(size=(300, cables, dof))
    # wrenches of tensions inside the range (in W) and a few far out
    t = rng.uniform(0.5, 4.5, size=(300, cables))
    wrenches = np.einsum("nkd,nk->nd", jacobians, t)
    margins = model.margins(jacobians, wrenches)
    agree = [
        _in_w(J.T, w, np.ones(cables), np.full(cables, 4.0)) == (m > 0)
        for J, w, m in zip(jacobians, wrenches, margins, strict=True)
        if abs(m) > 1e-6
    ]
    assert len(agree) >= 290 and all(agree)
    assert 20 <= sum(m > 0 for m in margins) <= 280


@pytest.mark.parametrize("parallel", [True, False])
def test_the_facet_normals_are_scipy_s_null_spaces_of_each_subset(
    reference8: Robot, parallel: bool
) -> None:
    """Each facet's normal is orthogonal to the m - 1 generators it is parallel to:
    scipy's null space of those columns of Lambda^T (SVD), up to sign, for every facet
    pair of random poses; the facets come in the order of the cables T off them."""
    jacobians, _ = _random_poses(reference8, 40, seed=5)
    normals = facet_normals(jacobians, parallel=parallel)
    n, dof = jacobians.shape[1:]
    off = list(itertools.combinations(range(n), n - dof + 1))
    assert normals.shape == (len(jacobians), len(off), dof)
    for J, found in zip(jacobians, normals, strict=True):
        for f, cables in enumerate(off):
            parallel_to = [j for j in range(n) if j not in cables]
            [expected] = null_space(J[parallel_to]).T  # one direction: the facet exists
            assert min(np.abs(found[f] - expected).max(), np.abs(found[f] + expected).max()) < 1e-9


def test_a_rank_deficient_jacobian_has_no_margin() -> None:
    model = WrenchMargin(np.ones(8), np.full(8, 4.0), 1.0)
    J = np.zeros((8, 6))
    J[:, 0] = 1.0  # every cable pulls along x
    assert model.margin(J, np.zeros(6)).value == -np.inf


def test_the_rest_wrench_is_the_robot_s_own_gravity_term(reference8: Robot) -> None:
    rng = np.random.default_rng(6)
    for _ in range(5):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        pose = Pose(rng.uniform(-0.5, 0.5, 3) + np.array([0.0, 0.0, 1.2]), q)
        expected = -reference8.bias_wrench(pose, np.zeros(6))
        got = rest_wrenches(reference8.platform, pose.rotation[None])[0]
        np.testing.assert_allclose(got, expected, atol=1e-12)
    # a payload at the centre of mass weighs like a heavier platform
    heavy = rest_wrenches(reference8.platform, np.eye(3)[None], 5.0, (0.0, 0.0, -0.02))[0]
    plain = rest_wrenches(reference8.platform, np.eye(3)[None])[0]
    np.testing.assert_allclose(heavy, plain * 15.0 / 10.0)


def test_bad_limits_are_refused_naming_them() -> None:
    with pytest.raises(ValueError, match="t_lo < t_hi"):
        WrenchMargin(np.full(8, 5.0), np.full(8, 4.0), 1.0)
    with pytest.raises(ValueError, match="5 cables cannot"):
        WrenchMargin(np.ones(5), np.full(5, 4.0), 1.0)


def test_the_bound_never_exceeds_the_margin_and_short_of_is_the_margins_verdict(
    reference8: Robot,
) -> None:
    """margin_bound_kernel's ball lies in W: never above the exact margin (and within a
    factor of it for most poses, or it would spare nothing); short_of(required) says
    exactly what margins() < required says, at thresholds across the margins found."""
    from cdpr.wrench_margin import margin_bound_kernel, margin_scratch

    robot = reference8
    model = WrenchMargin(robot.t_min, robot.force_max, wrench_length(robot.geometry.attachments))
    jacobians, wrenches = _random_poses(robot, 300, seed=7)
    margins = model.margins(jacobians, wrenches, parallel=False)
    A, w = model._scaled(jacobians, wrenches)
    work = margin_scratch(A.shape[1], A.shape[2])
    bounds = np.array(
        [margin_bound_kernel(A[p], w[p], model.t_lo, model.t_hi, work) for p in range(len(A))]
    )
    assert np.all(bounds <= margins + 1e-9)
    inside = margins > 0.0
    assert np.median(bounds[inside] / margins[inside]) > 0.3
    for required in (-5.0, 0.0, 5.0, float(np.median(margins)), 200.0):
        assert model.short_of(jacobians, wrenches, required).tolist() == (
            margins < required
        ).tolist()
