"""Tension distribution F and wrench-set membership W (cdpr/tension.py, DESIGN §6).

Inputs come from the model: tau = M alpha + mu, f0 = m0 (Lambda alpha + c),
f_b = k0 Lambda phi.  Constraints are checked in the original force formulation
(Lambda^T f = tau, f0 - f >= t_min, |f + f_b| <= force_max), independently of the
tension-space form the solvers use.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from cdpr import Pose, Robot
from cdpr.tension import (
    ClosedFormTensionSolver,
    OsqpTensionSolver,
    TensionLimits,
    TensionResult,
    make_tension_solver,
)
from tests.conftest import load_robot, pose_near_home, twists, workspace_poses

DATA = Path(__file__).resolve().parents[1] / "data"

SOLVERS = [OsqpTensionSolver, ClosedFormTensionSolver]

# near home with moderate motion both example robots stay inside W (checked below)
NEAR = workspace_poses(reach=0.2, tilt=0.1)
TWIST = twists(0.5)
ACCEL = twists(1.0)


def model_inputs(
    robot: Robot, pose: Pose, twist: np.ndarray, alpha: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(Lambda, tau, f_b, f0) for the control cycle at (pose, twist) commanding alpha."""
    L = robot.jacobian(pose)
    M, mu = robot.dynamics(pose, twist)
    tau = M @ alpha + mu
    f0 = robot.m0 * (L @ alpha + robot.bias_accel(pose, twist))
    f_b = robot.k0 * (L @ twist)
    return L, tau, f_b, f0


def tolerance(limits: TensionLimits, f_b: np.ndarray, f0: np.ndarray) -> float:
    """The documented check tolerance: 1e-6 x max(max force_max, max t_hi)."""
    return 1e-6 * max(limits.force_max.max(), (f0 + f_b + limits.force_max).max())


def assert_satisfies(res: TensionResult, L, tau, f_b, f0, limits: TensionLimits) -> None:
    tol = tolerance(limits, f_b, f0)
    assert res.feasible, res.reason
    assert res.reason == ""
    f, t = res.forces, res.tensions
    np.testing.assert_allclose(t, f0 - f, rtol=0, atol=1e-9)
    assert np.abs(L.T @ f - tau).max() <= tol
    assert np.all(t >= limits.t_min - tol)
    assert np.all(np.abs(f + f_b) <= limits.force_max + tol)


def equality_least_squares(L, tau, f0, t_ref) -> np.ndarray:
    """argmin |t - t_ref|^2 s.t. Lambda^T t = Lambda^T f0 - tau, via the KKT system."""
    n = L.shape[0]
    K = np.block([[np.eye(n), L], [L.T, np.zeros((6, 6))]])
    return np.linalg.solve(K, np.concatenate([t_ref, L.T @ f0 - tau]))[:n]


def bounds(limits: TensionLimits, f_b, f0) -> tuple[np.ndarray, np.ndarray]:
    g = f0 + f_b
    return np.maximum(limits.t_min, g - limits.force_max), g + limits.force_max


def objective(t: np.ndarray, limits: TensionLimits) -> float:
    return float(np.sum((t - limits.t_ref) ** 2))


def assert_kkt_optimal(t, L, limits: TensionLimits, lo, hi, tol: float = 1e-6) -> int:
    """t is optimal iff t - t_ref + Lambda nu = mu_lo - mu_hi with mu >= 0 on active bounds.
    Returns the number of active bounds."""
    at_lo = t <= lo + tol
    at_hi = t >= hi - tol
    free = ~(at_lo | at_hi)
    nu = np.linalg.lstsq(L[free], (limits.t_ref - t)[free], rcond=None)[0]
    s = t - limits.t_ref + L @ nu  # = mu_lo - mu_hi
    scale = max(1.0, float(np.abs(t - limits.t_ref).max()))
    assert np.abs(s[free]).max(initial=0.0) <= 1e-6 * scale
    assert np.all(s[at_lo] >= -1e-6 * scale)
    assert np.all(s[at_hi] <= 1e-6 * scale)
    return int((at_lo | at_hi).sum())


# -- feasible answers satisfy the constraints ----------------------------------------


@pytest.mark.parametrize("solver_cls", SOLVERS)
@settings(max_examples=60)
@given(offset=NEAR, twist=TWIST, alpha=ACCEL)
def test_feasible_near_home_and_constraints_hold(robot, solver_cls, offset, twist, alpha):
    limits = TensionLimits.from_robot(robot)
    solver = solver_cls(limits)
    L, tau, f_b, f0 = model_inputs(robot, pose_near_home(robot, offset), twist, alpha)
    assert_satisfies(solver.solve(L, tau, f_b, f0), L, tau, f_b, f0, limits)


@settings(max_examples=60)
@given(offset=NEAR, twist=TWIST, alpha=ACCEL)
def test_osqp_equals_exact_least_squares_when_no_bound_is_active(robot, offset, twist, alpha):
    limits = TensionLimits.from_robot(robot)
    L, tau, f_b, f0 = model_inputs(robot, pose_near_home(robot, offset), twist, alpha)
    exact = equality_least_squares(L, tau, f0, limits.t_ref)
    lo, hi = bounds(limits, f_b, f0)
    assert np.all(exact > lo + 1.0) and np.all(exact < hi - 1.0)  # no bound active
    for shortcut in (False, True):
        res = OsqpTensionSolver(limits, interior_shortcut=shortcut).solve(L, tau, f_b, f0)
        assert res.feasible, res.reason
        np.testing.assert_allclose(res.tensions, exact, rtol=0, atol=1e-6)
        assert (res.iterations == 0) == shortcut  # OSQP ran only without the shortcut


@settings(max_examples=60)
@given(offset=NEAR, twist=TWIST, alpha=ACCEL)
def test_closed_form_equals_osqp_when_no_bound_is_active(robot, offset, twist, alpha):
    limits = TensionLimits.from_robot(robot)
    L, tau, f_b, f0 = model_inputs(robot, pose_near_home(robot, offset), twist, alpha)
    cf = ClosedFormTensionSolver(limits).solve(L, tau, f_b, f0)
    qp = OsqpTensionSolver(limits).solve(L, tau, f_b, f0)
    assert cf.feasible and qp.feasible
    assert cf.iterations == 0
    np.testing.assert_allclose(cf.tensions, qp.tensions, rtol=0, atol=1e-6)
    np.testing.assert_allclose(cf.forces, qp.forces, rtol=0, atol=1e-6)
    exact = equality_least_squares(L, tau, f0, limits.t_ref)
    np.testing.assert_allclose(cf.tensions, exact, rtol=0, atol=1e-8)


def test_closed_form_is_the_unique_solution_without_redundancy():
    robot = load_robot("suspended6")
    limits = TensionLimits.from_robot(robot)
    pose = Pose.from_rotvec(robot.home.position + np.array([0.05, -0.1, 0.02]), [0.03, 0, -0.05])
    L, tau, f_b, f0 = model_inputs(robot, pose, np.full(6, 0.1), np.full(6, 0.3))
    unique = np.linalg.solve(L.T, L.T @ f0 - tau)
    for solver_cls in SOLVERS:
        res = solver_cls(limits).solve(L, tau, f_b, f0)
        assert res.feasible, res.reason
        np.testing.assert_allclose(res.tensions, unique, rtol=0, atol=1e-6)


# -- active bounds: OSQP is the optimum, the closed form is feasible but not better ----------

LOW_REF = 15.0  # t_ref this far above t_min pushes some cables onto t_min


def low_reference_limits(robot: Robot) -> TensionLimits:
    return TensionLimits.from_robot(robot, t_ref=robot.t_min + LOW_REF)


@settings(max_examples=60)
@given(offset=NEAR, twist=TWIST, alpha=ACCEL)
def test_active_bounds_osqp_optimal_and_closed_form_not_better(reference8, offset, twist, alpha):
    limits = low_reference_limits(reference8)
    pose = pose_near_home(reference8, offset)
    L, tau, f_b, f0 = model_inputs(reference8, pose, twist, alpha)
    lo, hi = bounds(limits, f_b, f0)
    qp = OsqpTensionSolver(limits).solve(L, tau, f_b, f0)
    assert_satisfies(qp, L, tau, f_b, f0, limits)
    assert assert_kkt_optimal(qp.tensions, L, limits, lo, hi) >= 1  # bounds really active
    cf = ClosedFormTensionSolver(limits).solve(L, tau, f_b, f0)
    if cf.feasible:  # Pott's method is a heuristic: it may miss feasible wrenches
        assert_satisfies(cf, L, tau, f_b, f0, limits)
        obj_qp, obj_cf = objective(qp.tensions, limits), objective(cf.tensions, limits)
        assert obj_cf >= obj_qp - 1e-9 * max(1.0, obj_qp)
    else:
        assert "t_min" in cf.reason or "force_max" in cf.reason


def test_active_bounds_closed_form_mostly_feasible_never_better(reference8):
    """Over a fixed sample with active bounds, the closed form finds most of OSQP's
    feasible answers (Pott's method is greedy) and none better than OSQP's."""
    limits = low_reference_limits(reference8)
    qp_solver, cf_solver = OsqpTensionSolver(limits), ClosedFormTensionSolver(limits)
    rng = np.random.default_rng(7)
    both = active = 0
    for _ in range(200):
        pose = Pose.from_rotvec(
            reference8.home.position + rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)
        )
        args = model_inputs(reference8, pose, rng.uniform(-0.5, 0.5, 6), rng.uniform(-1, 1, 6))
        qp, cf = qp_solver.solve(*args), cf_solver.solve(*args)
        assert qp.feasible, qp.reason
        lo, hi = bounds(limits, args[2], args[3])
        active += assert_kkt_optimal(qp.tensions, args[0], limits, lo, hi) > 0
        if cf.feasible:
            both += 1
            obj_qp = objective(qp.tensions, limits)
            assert objective(cf.tensions, limits) >= obj_qp - 1e-9 * max(1.0, obj_qp)
    assert active >= 150
    assert both >= 150


# -- infeasible wrenches -------------------------------------------------------------


UP = np.array([0.0, 0.0, 1e5, 0.0, 0.0, 0.0])  # a huge upward force (N)


@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_huge_upward_force_is_infeasible_naming_the_limit(robot, solver_cls):
    limits = TensionLimits.from_robot(robot)
    L, tau, f_b, f0 = model_inputs(robot, robot.home, np.zeros(6), np.zeros(6))
    res = solver_cls(limits).solve(L, tau + UP, f_b, f0)
    assert not res.feasible
    assert re.search(r"cable \d+ .*(force_max|t_min)", res.reason), res.reason
    if solver_cls is OsqpTensionSolver or robot.n_cables == 6:
        # the upper cables hit their force limit first
        assert "force_max" in res.reason
    assert np.all(np.isfinite(res.forces)) and np.all(np.isfinite(res.tensions))


@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_wrench_needing_negative_tension_is_infeasible_naming_t_min(solver_cls):
    """Pulling a suspended platform down needs cables that push."""
    robot = load_robot("suspended6")
    limits = TensionLimits.from_robot(robot)
    L, tau, f_b, f0 = model_inputs(robot, robot.home, np.zeros(6), np.zeros(6))
    down = tau - [0.0, 0.0, 3.0 * 9.81 * robot.spec.platform.mass, 0.0, 0.0, 0.0]
    res = solver_cls(limits).solve(L, down, f_b, f0)
    assert not res.feasible
    assert "t_min" in res.reason and "cable" in res.reason
    if solver_cls is ClosedFormTensionSolver:
        assert "below t_min" in res.reason


def test_closed_form_reports_rank_deficient_reduced_jacobian(reference8):
    """At the symmetric home pose fixing two cables can leave a singular 6-cable set;
    the reason names both the violated limit and the rank deficiency."""
    limits = TensionLimits.from_robot(reference8)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    res = ClosedFormTensionSolver(limits).solve(L, tau + UP, f_b, f0)
    assert not res.feasible
    assert "rank deficient" in res.reason and "cable" in res.reason


@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_unreachable_t_min_is_infeasible(reference8, solver_cls):
    """f0 + f_b + force_max < t_min: no actuator force keeps the cable taut."""
    limits = TensionLimits.from_robot(reference8)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    f_b = f_b.copy()
    f_b[2] = -700.0
    res = solver_cls(limits).solve(L, tau, f_b, f0)
    assert not res.feasible
    assert res.reason.startswith("cable 2: t_min 20 N unreachable")
    assert np.all(np.isfinite(res.tensions))


def test_osqp_recovers_after_infeasible_cycle(reference8):
    """An infeasible cycle resets the warm start; the next answers are right again."""
    limits = TensionLimits.from_robot(reference8)
    solver = OsqpTensionSolver(limits)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    good = solver.solve(L, tau, f_b, f0)
    assert good.feasible
    assert not solver.solve(L, tau + UP, f_b, f0).feasible
    again = solver.solve(L, tau, f_b, f0)
    assert again.feasible, again.reason
    np.testing.assert_allclose(again.tensions, good.tensions, rtol=0, atol=1e-6)


# -- the check is applied to every answer ----------------------------------------------


def test_osqp_answer_violating_equality_is_rejected(reference8):
    limits = TensionLimits.from_robot(reference8)
    solver = OsqpTensionSolver(limits, interior_shortcut=False)  # the OSQP path
    args = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    real_run = solver._run

    def off_by_a_bit(eps=None):
        x, status, polish, it = real_run(eps)
        x[0] += 0.01  # 10 mN: far inside the bounds, far outside the 1 mN tolerance
        return x, status, polish, it  # still "solved" and "polished"

    solver._run = off_by_a_bit
    res = solver.solve(*args)
    assert not res.feasible
    assert "wrench equality residual" in res.reason


def test_osqp_answer_violating_t_min_is_rejected(reference8):
    """A solution that keeps the wrench but drops cable 0 to 5 N is caught, and the
    reason names the worst cable below t_min."""
    limits = TensionLimits.from_robot(reference8)
    solver = OsqpTensionSolver(limits, interior_shortcut=False)  # the OSQP path
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    null = np.linalg.svd(L.T)[2][-1]  # Lambda^T null = 0
    real_run = solver._run
    slack = []

    def slack_cable_0(eps=None):
        x, status, polish, it = real_run(eps)
        slack.append(x - (x[0] - 5.0) / null[0] * null)
        return slack[-1], status, polish, it

    solver._run = slack_cable_0
    res = solver.solve(L, tau, f_b, f0)
    assert not res.feasible
    t = slack[-1]
    assert np.abs(L.T @ (f0 - t) - tau).max() < 1e-9  # only the bound is violated
    k = int(np.argmax(limits.t_min - t))
    assert res.reason == f"cable {k} tension {t[k]:.4g} N below t_min 20 N"


def test_osqp_refines_when_polishing_fails(reference8):
    """A solve whose polish failed is re-solved at tighter tolerance before any verdict."""
    limits = TensionLimits.from_robot(reference8)
    solver = OsqpTensionSolver(limits, interior_shortcut=False)  # the OSQP path
    args = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    calls = []
    real_run = solver._run

    def polish_fails_once(eps=None):
        x, status, polish, it = real_run(eps)
        calls.append(eps)
        return (x + 0.5, status, -1, it) if len(calls) == 1 else (x, status, polish, it)

    solver._run = polish_fails_once
    res = solver.solve(*args)
    assert res.feasible, res.reason
    assert calls == [None, 1e-7]
    L, tau, _, f0 = args
    exact = equality_least_squares(L, tau, f0, limits.t_ref)
    np.testing.assert_allclose(res.tensions, exact, rtol=0, atol=1e-6)


def test_osqp_rejected_update_is_infeasible_not_solved(reference8):
    """If osqp refuses a data update it keeps the old data: never report that solution."""
    limits = TensionLimits.from_robot(reference8)
    solver = OsqpTensionSolver(limits, interior_shortcut=False)  # the OSQP path
    args = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    assert solver.solve(*args).feasible

    class Refusing:
        def __init__(self, inner):
            self._inner = inner

        def __getattr__(self, name):
            return getattr(self._inner, name)

        def update_data_mat(self, *args):
            return 1

    solver._solver = Refusing(solver._solver)
    res = solver.solve(*args)
    assert not res.feasible
    assert res.reason == "osqp rejected the data update"
    assert np.all(np.isfinite(res.tensions))


# -- warm start along a path, through a pose where Lambda has exact zeros ------------------


def test_warm_started_path_through_exact_zeros_stays_correct(reference8):
    """Down to where the lower cables are horizontal (exact zeros in Lambda) and back, one
    solver warm-started all the way, each answer equal to a cold solve.  Regression for the
    CSC pitfall: scipy's csc_matrix drops those zeros, and value updates then misalign."""
    limits = TensionLimits.from_robot(reference8)
    warm = OsqpTensionSolver(limits)
    home = reference8.home.position
    # platform height at which the lower cables (anchors on the floor) run horizontally
    flat = max(
        a - b
        for a, b in zip(
            reference8.geometry.anchors[:, 2], reference8.geometry.attachments[:, 2], strict=True
        )
        if a == 0.0
    )
    zs = np.concatenate([np.linspace(home[2], flat, 60), np.linspace(flat, home[2], 60)])
    zs[59] = zs[60] = flat
    saw_zeros = 0
    for i, z in enumerate(zs):
        s = i / (len(zs) - 1)
        pose = Pose.from_rotvec([0.05 * np.sin(6 * s) * (z != flat), 0.0, z], [0.0, 0.0, 0.0])
        twist = np.array([0.0, 0.0, -0.2 if i < 60 else 0.2, 0.0, 0.0, 0.0]) * (z != flat)
        L, tau, f_b, f0 = model_inputs(reference8, pose, twist, np.zeros(6))
        if np.count_nonzero(L == 0.0) >= 4:
            saw_zeros += 1
            A = np.vstack([L.T, np.eye(8)])
            assert sp.csc_matrix(A).nnz < 7 * 8  # the pitfall is real at this pose
        res = warm.solve(L, tau, f_b, f0)
        assert_satisfies(res, L, tau, f_b, f0, limits)
        cold = OsqpTensionSolver(limits).solve(L, tau, f_b, f0)
        np.testing.assert_allclose(res.tensions, cold.tensions, rtol=0, atol=1e-6)
    assert saw_zeros >= 2
    # a solver whose very first problem has the zeros, then a generic pose
    first = OsqpTensionSolver(limits)
    for pose in (Pose([0.0, 0.0, flat]), reference8.home):
        L, tau, f_b, f0 = model_inputs(reference8, pose, np.zeros(6), np.zeros(6))
        res = first.solve(L, tau, f_b, f0)
        assert_satisfies(res, L, tau, f_b, f0, limits)
        exact = equality_least_squares(L, tau, f0, limits.t_ref)
        np.testing.assert_allclose(res.tensions, exact, rtol=0, atol=1e-6)


@settings(max_examples=10)
@given(start=NEAR, step=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)))
def test_warm_started_smooth_path_matches_closed_form(reference8, start, step):
    """A 1 kHz-like path: both solvers stay feasible and equal at every step."""
    limits = TensionLimits.from_robot(reference8)
    qp, cf = OsqpTensionSolver(limits), ClosedFormTensionSolver(limits)
    p0 = pose_near_home(reference8, start).position
    for k in range(50):
        s = k * 2e-3
        p = p0 + 0.05 * np.array([np.sin(step[0] * s), np.sin(step[1] * s), 0.1 * s])
        twist = 0.05 * np.array([step[0], step[1], 0.1, 0.0, 0.0, 0.0])
        args = model_inputs(reference8, Pose(p), twist, np.array([0.5, -0.5, 0.2, 0, 0, 0]))
        a, b = qp.solve(*args), cf.solve(*args)
        assert a.feasible and b.feasible
        np.testing.assert_allclose(a.tensions, b.tensions, rtol=0, atol=1e-6)


def test_direct_and_wrapper_paths_agree(reference8):
    """Driving osqp's compiled solver directly gives what osqp's public wrappers give."""
    limits = low_reference_limits(reference8)
    direct, wrapped = OsqpTensionSolver(limits), OsqpTensionSolver(limits, direct=False)
    assert direct.direct and not wrapped.direct
    rng = np.random.default_rng(3)
    for _ in range(30):
        pose = Pose.from_rotvec(
            reference8.home.position + rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)
        )
        args = model_inputs(reference8, pose, rng.uniform(-0.5, 0.5, 6), rng.uniform(-1, 1, 6))
        a, b = direct.solve(*args), wrapped.solve(*args)
        assert a.feasible and b.feasible
        np.testing.assert_allclose(a.tensions, b.tensions, rtol=0, atol=1e-6)
    huge = (args[0], args[1] + UP, args[2], args[3])
    assert direct.solve(*huge).reason == wrapped.solve(*huge).reason


# -- bad inputs ----------------------------------------------------------------------


@pytest.mark.parametrize("solver_cls", SOLVERS)
@pytest.mark.parametrize("name", ["jacobian", "wrench", "f_b", "f0"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_is_infeasible_not_an_exception(reference8, solver_cls, name, bad):
    limits = TensionLimits.from_robot(reference8)
    solver = solver_cls(limits)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    args = {"jacobian": L, "wrench": tau, "f_b": f_b, "f0": f0}
    args = {k: v.copy() for k, v in args.items()}
    args[name].flat[1] = bad
    res = solver.solve(**args)
    assert not res.feasible
    assert res.reason == f"non-finite input: {name}"
    assert np.all(np.isnan(res.forces)) and np.all(np.isnan(res.tensions))
    # and the solver still works afterwards
    assert solver.solve(L, tau, f_b, f0).feasible


@pytest.mark.parametrize("solver_cls", SOLVERS)
@pytest.mark.parametrize(
    ("name", "shape"),
    [("jacobian", (6, 8)), ("jacobian", (8,)), ("wrench", (5,)), ("f_b", (7,)), ("f0", (8, 1))],
)
def test_wrong_shape_raises_naming_the_argument(reference8, solver_cls, name, shape):
    limits = TensionLimits.from_robot(reference8)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    args = {"jacobian": L, "wrench": tau, "f_b": f_b, "f0": f0}
    args[name] = np.zeros(shape)
    with pytest.raises(ValueError, match=name):
        solver_cls(limits).solve(**args)


def test_lists_are_accepted(reference8):
    limits = TensionLimits.from_robot(reference8)
    L, tau, f_b, f0 = model_inputs(reference8, reference8.home, np.zeros(6), np.zeros(6))
    res = ClosedFormTensionSolver(limits).solve(L.tolist(), tau.tolist(), list(f_b), list(f0))
    assert res.feasible
    with pytest.raises(ValueError, match="wrench"):
        ClosedFormTensionSolver(limits).solve(L, ["a"] * 6, f_b, f0)


# -- factory and limits ----------------------------------------------------------------


def test_make_tension_solver(reference8):
    limits = TensionLimits.from_robot(reference8)
    assert isinstance(make_tension_solver("osqp", limits), OsqpTensionSolver)
    cf = make_tension_solver("closed_form", limits)
    assert isinstance(cf, ClosedFormTensionSolver) and cf.method == "closed_form"
    assert make_tension_solver("osqp", limits, max_iter=50).method == "osqp"
    with pytest.raises(ValueError, match=r"'lp'.*allowed: 'osqp', 'closed_form'"):
        make_tension_solver("lp", limits)


def test_limits_from_robot_default_and_scalar_reference(reference8):
    limits = TensionLimits.from_robot(reference8)
    assert limits.n == 8
    np.testing.assert_array_equal(limits.t_ref, np.full(8, (20.0 + 600.0) / 2))
    np.testing.assert_array_equal(limits.t_min, reference8.t_min)
    np.testing.assert_array_equal(limits.force_max, reference8.force_max)
    assert not limits.t_ref.flags.writeable
    np.testing.assert_array_equal(TensionLimits.from_robot(reference8, 100.0).t_ref, 100.0)


@pytest.mark.parametrize(
    ("t_min", "force_max", "t_ref", "message"),
    [
        ([20, 20], [600, 600, 600], [300, 300], "force_max has 3 values but t_min has 2"),
        ([20, 20], [600, 600], [300], "t_ref has 1 values but t_min has 2"),
        ([20, 20], [600, 600], [300, 700], r"cable 1: t_ref 700 N outside \[t_min 20 N, "),
        ([20, 20], [600, 600], [10, 300], "cable 0: t_ref 10 N outside"),
        ([20, 700], [600, 600], [300, 650], "cable 1: t_min 700 N exceeds force_max 600 N"),
        ([-1, 20], [600, 600], [300, 300], "cable 0: t_min -1 N is negative"),
        ([20, 20], [600, 0], [300, 0], "cable 1: force_max 0 N must be positive"),
        ([20, np.nan], [600, 600], [300, 300], "t_min has non-finite values"),
        ([[20, 20]], [600, 600], [300, 300], "t_min needs one value per cable"),
        ([20, 20], ["x", 600], [300, 300], "force_max is not an array of numbers"),
    ],
)
def test_limits_validation_messages(t_min, force_max, t_ref, message):
    with pytest.raises(ValueError, match=message):
        TensionLimits(t_min, force_max, t_ref)


# -- membership of W against an independent LP ------------------------------------------


def lp_margin(L, tau, f_b, f0, limits: TensionLimits) -> float:
    """The largest s such that some forces f with Λᵀ f = τ keep every tension t = f0 − f
    at least s inside [t_min, force_max] (|f + f_b| ≤ force_max), by scipy's HiGHS LP in
    the force formulation: written apart from both solvers.  > 0 inside W, < 0 outside."""
    n = len(f0)
    # variables: f (n), s; maximise s
    cost = np.zeros(n + 1)
    cost[-1] = -1.0
    eye, ones = np.eye(n), np.ones((n, 1))
    a_ub = np.vstack(
        [
            np.hstack([eye, ones]),  # f0 - f >= t_min + s
            np.hstack([eye, ones]),  # f + f_b <= force_max - s
            np.hstack([-eye, ones]),  # f + f_b >= -force_max + s
        ]
    )
    b_ub = np.concatenate([f0 - limits.t_min, limits.force_max - f_b, limits.force_max + f_b])
    a_eq = np.hstack([L.T, np.zeros((6, 1))])
    res = linprog(cost, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=tau, bounds=[(None, None)] * (n + 1))
    assert res.status == 0, res.message
    return float(res.x[-1])


@pytest.mark.parametrize("t_ref", [25.0, 100.0])
def test_both_methods_call_a_wrench_feasible_exactly_when_an_lp_does(reference8, t_ref):
    """Random poses, twists and demanding accelerations, many with bounds active: OSQP
    and the closed form say feasible exactly when the LP finds a margin (cases within
    1 mN of the boundary are left out: either answer is right there).  The closed form
    alone misses some feasible wrenches: those are the ones its exact fallback decides."""
    limits = TensionLimits.from_robot(reference8, t_ref=t_ref)
    osqp_solver, closed = OsqpTensionSolver(limits), ClosedFormTensionSolver(limits)
    rng = np.random.default_rng(19)
    verdicts = {"inside": 0, "outside": 0, "fallback": 0}
    for _ in range(300):
        pose = Pose.from_rotvec(
            reference8.home.position + rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.3, 0.3, 3)
        )
        twist = rng.uniform(-1.0, 1.0, 6)
        alpha = rng.uniform(-15.0, 15.0, 6)
        args = model_inputs(reference8, pose, twist, alpha)
        margin = lp_margin(*args, limits)
        if abs(margin) < 1e-3:
            continue
        inside = margin > 0
        verdicts["inside" if inside else "outside"] += 1
        qp, cf = osqp_solver.solve(*args), closed.solve(*args)
        assert qp.feasible is inside, (margin, qp.reason)
        assert cf.feasible is inside, (margin, cf.reason)
        if cf.feasible:
            assert_satisfies(cf, *args, limits)
            verdicts["fallback"] += cf.iterations > 0  # OSQP iterated: Pott's missed it
    assert verdicts["inside"] >= 50 and verdicts["outside"] >= 50, verdicts
    if t_ref == 25.0:
        assert verdicts["fallback"] >= 1, verdicts


@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_a_factored_jacobian_gives_the_plain_solve(robot, solver_cls):
    """solve(factored(Λ), ...) (Λᵀ Λ factored ahead, as the controller does before the
    measurement) gives what solve(Λ, ...) gives: in the interior, with bounds active,
    beyond W, with t_min unreachable and for a rank-deficient Λ.  Two solvers fed the
    same sequence, since OSQP's warm start carries over."""
    limits = TensionLimits.from_robot(robot)
    plain, factored = solver_cls(limits), solver_cls(limits)
    rng = np.random.default_rng(5)
    outcomes = set()
    for k in range(60):
        pose = pose_near_home(robot, (rng.uniform(-0.2, 0.2, 3), rng.uniform(-0.1, 0.1, 3)))
        alpha = rng.standard_normal(6) * (0.5, 5.0, 15.0, 40.0)[k % 4]
        L, tau, f_b, f0 = model_inputs(robot, pose, 0.2 * rng.standard_normal(6), alpha)
        if k % 20 == 18:
            L[:, 5] = 0.0  # rank deficient
        if k % 20 == 9:
            f_b = f_b - 2 * limits.force_max  # t_min unreachable
        a = plain.solve(L, tau, f_b, f0)
        b = factored.solve(factored.factored(L), tau, f_b, f0)
        assert (a.feasible, a.reason, a.iterations) == (b.feasible, b.reason, b.iterations)
        np.testing.assert_array_equal(a.tensions, b.tensions)
        np.testing.assert_array_equal(a.forces, b.forces)
        outcomes.add((a.feasible, a.iterations > 0, a.reason[:12]))
    feasible = {f for f, _, _ in outcomes}
    assert feasible == {True, False} and len(outcomes) >= 4, outcomes


@pytest.mark.parametrize("solver_cls", SOLVERS)
def test_a_floor_keeps_every_cable_above_t_min_where_tensions_can_be(reference8, solver_cls):
    """With a 5 N floor, a wrench that tensions at least t_min + 5 N can carry (scipy's LP)
    gets the optimum over those; one that only tensions down to t_min can carry gets
    what the solver without a floor gives (the optimum over [t_min, ...], a cable below
    the floor); one that none can carry is infeasible, naming the limit.  Low reference
    tensions, so the bounds are active in most cases; a fresh solver for each, so no
    warm start carries over.  (OSQP without a floor misses 1 of these 300 wrenches, 0.44 N
    inside W: the band below the floor is held to it, not to the LP.)"""
    floor = 5.0
    plain = TensionLimits.from_robot(reference8, t_ref=25.0)
    floored = TensionLimits.from_robot(reference8, t_ref=25.0, floor=floor)
    raised = TensionLimits(plain.t_min + floor, plain.force_max, plain.t_ref)  # for the LP
    rng = np.random.default_rng(23)
    cases = {"above the floor": 0, "below the floor": 0, "outside": 0}
    for _ in range(300):
        pose = Pose.from_rotvec(
            reference8.home.position + rng.uniform(-0.3, 0.3, 3), rng.uniform(-0.3, 0.3, 3)
        )
        args = model_inputs(reference8, pose, rng.uniform(-1, 1, 6), rng.uniform(-15, 15, 6))
        above, anywhere = lp_margin(*args, raised), lp_margin(*args, plain)
        if min(abs(above), abs(anywhere)) < 1e-3:
            continue  # within 1 mN of a boundary: either answer is right
        result = solver_cls(floored).solve(*args)
        if above > 0:
            cases["above the floor"] += 1
            assert_satisfies(result, *args, raised)
            if solver_cls is OsqpTensionSolver:
                assert_kkt_optimal(result.tensions, args[0], raised, *bounds(raised, *args[2:]))
        elif anywhere > 0:
            assert result.feasible is solver_cls(plain).solve(*args).feasible
            if result.feasible:
                cases["below the floor"] += 1
                assert_satisfies(result, *args, plain)
                assert result.tensions.min() < plain.t_min.min() + floor
                if solver_cls is OsqpTensionSolver:
                    lo, hi = bounds(plain, *args[2:])
                    assert_kkt_optimal(result.tensions, args[0], plain, lo, hi)
        else:
            cases["outside"] += 1
            assert not result.feasible
            assert "t_min" in result.reason or "force_max" in result.reason, result.reason
    assert min(cases.values()) >= 5, cases


def test_a_floor_must_be_a_number_at_least_zero():
    for bad in (-1.0, np.nan, "x"):
        with pytest.raises(ValueError, match="floor must be a number >= 0"):
            TensionLimits([20.0], [600.0], [300.0], bad)


def test_osqp_solves_the_problem_its_timed_rho_adaptation_stalled_on(reference8):
    """A wrench 1.9 N inside W (tests/data/osqp_rho_stall.json: its margin by the LP
    here, scipy's HiGHS) on which OSQP with osqp's default rho adaptation, timed by its
    set-up, once ran rho away and stopped at its iteration limit, a false 'not in W'.
    That timing makes the stall a matter of luck, which no test can replay on demand;
    with rho adapted every ADAPTIVE_RHO_INTERVAL iterations the run is the same on any
    host: solved in one run (no cold restart), and both methods say feasible."""
    data = json.loads((DATA / "osqp_rho_stall.json").read_text())
    limits = TensionLimits.from_robot(reference8, t_ref=data["t_ref"])
    args = [np.array(data[k]) for k in ("jacobian", "wrench", "f_b", "f0")]
    assert lp_margin(*args, limits) == pytest.approx(data["lp_margin_N"], abs=1e-6)
    solver = OsqpTensionSolver(limits, interior_shortcut=False)
    result = solver.solve(*args)
    assert result.feasible, result.reason
    assert result.iterations < 4000  # solved, not retried from a cold start
    assert_satisfies(result, *args, limits)
    assert ClosedFormTensionSolver(limits).solve(*args).feasible
