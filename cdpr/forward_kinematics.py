"""Forward kinematics Y(l): Gauss-Newton / Levenberg-Marquardt on SE(3).

Steps are mixed tangent vectors (dp, dw) applied as (p + dp, exp(dw) R), for which the
Jacobian of the lengths is exactly Lambda.  n > 6 cables give a least-squares fit.
The solver never raises on a bad measurement (NaN, impossible lengths): it returns
``converged=False`` with a reason, and the caller (the daemon) decides to brake.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import cholesky, cholesky_solve, gram
from cdpr.kinematics import AT_REST, CableGeometry, pose_rows
from cdpr.pose import Pose
from cdpr.so3 import quat_mul4, rotvec_to_quat4

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]
_rotvec_to_quat4 = njit(cache=True)(rotvec_to_quat4)  # so3's, callable from the kernels
_quat_mul4 = njit(cache=True)(quat_mul4)


class FKResult(NamedTuple):
    """Outcome of Y(l): the pose, RMS length residual (m), iterations, and why not converged.

    `jacobian` is Lambda at the solver's last linearisation point, less than one step
    tolerance-scale step (<= 1e-4 m / rad) from `pose` when converged: accurate enough
    for the least-squares twist of the same cycle, and free.  `normal_factor` is the
    Cholesky factor of jacobian^T jacobian (upper triangle, as LAPACK dpotrf leaves it),
    so that such a least-squares solve is one dpotrs call.  Both are None unless
    converged (the factor also where jacobian^T jacobian is singular).
    """

    pose: Pose
    residual: float
    iterations: int
    converged: bool
    reason: str = ""
    jacobian: np.ndarray | None = None
    normal_factor: np.ndarray | None = None


class Linearisation(NamedTuple):
    """What forward kinematics' first evaluation at `guess` needs of the guess alone
    (linearise): L(guess), Lambda(guess) (contiguous) and the Cholesky factor of its
    Gram matrix (the kernels' form, cdpr.compiled_linalg.cholesky; None where
    singular).  A control cycle computes it while the measured lengths are on their
    way; they then enter only through Lambda^T (L - l)."""

    guess: Pose
    lengths: np.ndarray
    jacobian: np.ndarray
    factor: np.ndarray | None


def linearise(geometry: CableGeometry, guess: Pose) -> Linearisation:
    """The measurement-free part of Y(l)'s first evaluation at `guess` (Linearisation)."""
    lengths, J, L, ok = _linearise(geometry.rows, guess.position_tuple, guess.quaternion_tuple)
    return Linearisation(guess, lengths, J, L if ok else None)


@dataclass(frozen=True)
class FKSettings:
    max_iterations: int = 50
    step_tolerance: float = 1e-8
    max_residual: float = 2e-3


def solve_forward_kinematics(
    geometry: CableGeometry,
    lengths: ArrayLike,
    guess: Pose | Linearisation,
    settings: FKSettings,
) -> FKResult:
    """Pose whose cable lengths best match `lengths` (least squares), started at `guess`
    (a pose, or linearise()'s linearisation at one, which saves the first evaluation).

    Gauss-Newton while it reduces the cost, Levenberg-Marquardt damping when a step
    does not.  A Gauss-Newton step shorter than step_tolerance (m, or rad) ends the
    iteration without a further evaluation: convergence is quadratic there, so the
    remaining error is of the order of the step squared.  Below 1e-4 (m, rad;
    _CHORD_BELOW2 is its square) a step reuses the last Jacobian and its factor (a
    chord step needs only the lengths).  The iteration and its verdict are one compiled
    kernel (fit_kernel).
    """
    start = None
    if type(guess) is Linearisation:
        start, guess = guess, guess.guess
    n = geometry.n
    measured = np.asarray(lengths, dtype=float).ravel()
    if measured.shape[0] != n:
        raise ValueError(f"expected {n} cable lengths, got {measured.shape[0]}")
    bad = non_finite_lengths(guess, measured)  # a NaN or inf among them
    if bad is not None:
        return bad
    if not (measured.flags.c_contiguous and measured.flags.writeable):
        measured = measured.copy()  # the one array type fit_kernel is compiled for
    kind, lengths0, J0, L0 = fit_start(start)
    status, iterations, residual, p, q, J, U, factored = fit_kernel(
        geometry.rows, measured, guess.position_tuple, guess.quaternion_tuple,
        kind, lengths0, J0, L0, settings.max_iterations, settings.step_tolerance**2,
        settings.max_residual,
    )  # fmt: skip
    return fit_result(guess, settings, status, iterations, residual, p, q, J, U, factored)


def non_finite_lengths(guess: Pose, measured: Array) -> FKResult | None:
    """The failed result naming the first NaN or inf among the lengths; None if all are
    finite (one sum says so in the usual case; a sum of finite lengths can overflow:
    such lengths fail the residual check)."""
    lengths = measured.tolist()
    if math.isfinite(sum(lengths)):
        return None
    for k, length in enumerate(lengths):
        if not math.isfinite(length):
            return FKResult(guess, math.inf, 0, False, f"non-finite length {length} at cable {k}")
    return None


def fit_start(start: Linearisation | None) -> tuple[int, Array, Array, Array]:
    """How fit_kernel starts (its `kind`, lengths0, J0, L0) from a linearisation or none."""
    if start is None:
        return _COLD, _NO_LENGTHS, _NO_JACOBIAN, _NO_FACTOR
    kind = _FACTORED if start.factor is not None else _LINEARISED
    return kind, start.lengths, start.jacobian, _NO_FACTOR if start.factor is None else start.factor


def fit_result(
    guess: Pose,
    settings: FKSettings,
    status: int,
    iterations: int,
    residual: float,
    p: Array,
    q: Array,
    J: Array,
    U: Array,
    factored: bool,
) -> FKResult:
    """FKResult of what fit_kernel returned (a kernel that runs it returns the same)."""
    if status == CONVERGED:
        return FKResult(Pose._from_unit(p.tolist(), q.tolist()), residual, iterations, True, "",
                        J, U if factored else None)  # fmt: skip
    if status == _DIVERGED:
        return FKResult(guess, math.inf, iterations, False, "diverged to non-finite values")
    if status == _SINGULAR:
        reason = "singular Jacobian"
    elif status == _NO_DESCENT:
        reason = "no descent direction"
    elif status == _NO_CONVERGENCE:
        reason = f"no convergence in {settings.max_iterations} iterations"
    else:
        reason = (
            f"length residual {residual:.3g} m exceeds max_residual {settings.max_residual:.3g} m"
        )
    return FKResult(Pose._from_unit(p.tolist(), q.tolist()), residual, iterations, False, reason)


_LM_START = 1e-4
_LM_GIVE_UP = 1e12
_CHORD_BELOW2 = 1e-4**2  # squared step length below which the chord finish is tried
# how fit_kernel starts: from the guess, or its linearisation with or without a factor
_COLD, _LINEARISED, _FACTORED = 0, 1, 2
# how fit_kernel ends: converged within max_residual, or why not
CONVERGED, _SINGULAR, _NO_DESCENT, _NO_CONVERGENCE, _DIVERGED, _RESIDUAL = 0, 1, 2, 3, 4, 5
_NO_LENGTHS, _NO_JACOBIAN, _NO_FACTOR = np.empty(0), np.empty((0, 6)), np.empty((6, 6))


@njit(cache=True)
def _linearise(
    cables: Array, p: tuple[float, float, float], q: tuple[float, float, float, float]
) -> tuple[Array, Array, Array, bool]:
    """(L, Lambda, the factor of Lambda^T Lambda, whether it is positive definite)."""
    n = cables.shape[0]
    table, lengths = np.empty((n, 7)), np.empty(n)
    pose_rows(cables, p, q, AT_REST, table, lengths)
    J = np.ascontiguousarray(table[:, :6])
    G, L = np.empty((6, 6)), np.zeros((6, 6))
    gram(J.T, G)
    return lengths, J, L, cholesky(G, L)


@njit(cache=True)
def _step(p: Array, q: Array, x: Array, p_new: Array, q_new: Array) -> float:
    """(p_new, q_new) = (p - dx, exp(-dw) q) for the step x = (dx, dw); its squared
    length max(|dx|^2, |dw|^2)."""
    p_new[0], p_new[1], p_new[2] = p[0] - x[0], p[1] - x[1], p[2] - x[2]
    aw, ax, ay, az = _rotvec_to_quat4(-x[3], -x[4], -x[5])
    w, a, b, c = _quat_mul4(aw, ax, ay, az, q[0], q[1], q[2], q[3])
    scale = 1.0 / math.sqrt(w * w + a * a + b * b + c * c)
    q_new[0], q_new[1], q_new[2], q_new[3] = w * scale, a * scale, b * scale, c * scale
    translation2 = x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
    return max(translation2, x[3] * x[3] + x[4] * x[4] + x[5] * x[5])


@njit(cache=True)
def _residuals(
    cables: Array, p: Array, q: Array, measured: Array, table: Array, e: Array
) -> float:
    """table = [Lambda | c] and e = L - measured at (p, q); |e|^2."""
    pose_rows(cables, (p[0], p[1], p[2]), (q[0], q[1], q[2], q[3]), AT_REST, table, e)
    cost = 0.0
    for k in range(e.shape[0]):
        e[k] -= measured[k]
        cost += e[k] * e[k]
    return cost


@njit(cache=True)
def fit_kernel(
    cables: Array,
    measured: Array,
    p0: tuple[float, float, float],
    q0: tuple[float, float, float, float],
    kind: int,
    lengths0: Array,
    J0: Array,
    L0: Array,
    max_iterations: int,
    tolerance2: float,
    max_residual: float,
) -> tuple[int, int, float, Array, Array, Array, Array, bool]:
    """_iterate, and its verdict: (status, iterations, RMS length residual (m), p, q,
    Lambda, U, whether U is one), status _DIVERGED for a non-finite pose and _RESIDUAL
    for a converged fit whose residual exceeds `max_residual` (fit_result says why)."""
    status, iterations, cost, p, q, J, U, factored = _iterate(
        cables, measured, p0, q0, kind, lengths0, J0, L0, max_iterations, tolerance2
    )
    residual = math.sqrt(max(cost, 0.0) / measured.shape[0]) if math.isfinite(cost) else math.inf
    if not math.isfinite(p[0] + p[1] + p[2] + q[0] + q[1] + q[2] + q[3]):
        status = _DIVERGED
    elif status == CONVERGED and residual > max_residual:
        status = _RESIDUAL
    return status, iterations, residual, p, q, J, U, factored


@njit(cache=True)
def _iterate(
    cables: Array,
    measured: Array,
    p0: tuple[float, float, float],
    q0: tuple[float, float, float, float],
    kind: int,
    lengths0: Array,
    J0: Array,
    L0: Array,
    max_iterations: int,
    tolerance2: float,
) -> tuple[int, int, float, Array, Array, Array, Array, bool]:
    """Gauss-Newton / Levenberg-Marquardt from (p0, q0) (solve_forward_kinematics; with
    kind _LINEARISED or _FACTORED its lengths, Lambda and factor there).  Returns
    (status, iterations, |e|^2 (linearised after the last step), p, q, Lambda at the
    last linearisation, the upper Cholesky factor U of its Lambda^T Lambda as LAPACK's
    dpotrf leaves it, whether U is one)."""
    n = cables.shape[0]
    p, q = np.array(p0), np.array(q0)
    p_new, q_new, p_chord, q_chord = np.empty(3), np.empty(4), np.empty(3), np.empty(4)
    table, e = np.empty((n, 7)), np.empty(n)
    J, G, A = np.empty((n, 6)), np.empty((6, 6)), np.empty((6, 6))
    L, g, x, g_chord = np.zeros((6, 6)), np.empty(6), np.empty(6), np.empty(6)
    factored = False
    if kind == _COLD:
        cost = _residuals(cables, p, q, measured, table, e)
        J[:, :] = table[:, :6]
    else:
        J[:, :] = J0
        cost = 0.0
        for k in range(n):
            e[k] = lengths0[k] - measured[k]
            cost += e[k] * e[k]
        if kind == _FACTORED:
            L[:, :] = L0
            factored = True
    gram(J.T, G)
    _project(J, e, g)
    lam = 0.0
    for it in range(1, max_iterations + 1):
        if factored:  # the prepared linearisation's, undamped
            factored = False
        else:
            A[:, :] = G
            if lam:
                for i in range(6):
                    A[i, i] *= 1.0 + lam
            if not cholesky(A, L):  # singular normal equations: damp harder
                lam = max(lam * 10.0, _LM_START)
                if lam > _LM_GIVE_UP:
                    return _SINGULAR, it, cost, p, q, J, L, False
                continue
        x[:] = g
        cholesky_solve(L, x)
        step2 = _step(p, q, x, p_new, q_new)
        if not lam and step2 < tolerance2:
            # linearised cost after the step: |e|^2 - g . A^-1 g
            return CONVERGED, it, cost - _dot(g, x), p_new, q_new, J, _upper(L), True
        cost_new = _residuals(cables, p_new, q_new, measured, table, e)
        if not lam and step2 < _CHORD_BELOW2:
            # quadratic regime: one more step with this factor and Jacobian needs only
            # the lengths; its error is ~ step x next step, far below tolerance
            _project(J, e, g_chord)
            x[:] = g_chord
            cholesky_solve(L, x)
            if _step(p_new, q_new, x, p_chord, q_chord) < tolerance2:
                cost_chord = cost_new - _dot(g_chord, x)
                return CONVERGED, it + 1, cost_chord, p_chord, q_chord, J, _upper(L), True
        if cost_new <= cost or not math.isfinite(cost):
            p[:] = p_new
            q[:] = q_new
            cost = cost_new
            J[:, :] = table[:, :6]
            gram(J.T, G)
            _project(J, e, g)
            lam = lam * 0.1 if lam > _LM_START else 0.0
            if step2 < tolerance2:
                if cholesky(G, L):
                    return CONVERGED, it, cost, p, q, J, _upper(L), True
                return CONVERGED, it, cost, p, q, J, L, False
        else:
            lam = max(lam * 10.0, _LM_START)
            if lam > _LM_GIVE_UP:
                return _NO_DESCENT, it, cost, p, q, J, L, False
    return _NO_CONVERGENCE, max_iterations, cost, p, q, J, L, False


@njit(cache=True)
def _dot(a: Array, b: Array) -> float:
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@njit(cache=True)
def _project(J: Array, e: Array, g: Array) -> None:
    """g = J^T e."""
    for a in range(6):
        s = 0.0
        for k in range(e.shape[0]):
            s += J[k, a] * e[k]
        g[a] = s


@njit(cache=True)
def _upper(L: Array) -> Array:
    """The upper factor U = L^T (U^T U = G, LAPACK's layout) of cholesky's L."""
    U = np.zeros((6, 6))
    for i in range(6):
        U[i, i] = 1.0 / L[i, i]
        for j in range(i):
            U[j, i] = L[i, j]
    return U
