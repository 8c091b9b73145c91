"""Forward kinematics Y(l): Gauss-Newton / Levenberg-Marquardt on SE(3).

Steps are mixed tangent vectors (dp, dw) applied as (p + dp, exp(dw) R), for which the
Jacobian of the lengths is exactly Lambda.  n > 6 cables give a least-squares fit.
The solver never raises on a bad measurement (NaN, impossible lengths): it returns
``converged=False`` with a reason, and the caller (the daemon) decides to brake.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg.lapack import dposv, dpotrf, dpotrs

from cdpr.kinematics import CableGeometry, to_array
from cdpr.pose import Pose
from cdpr.so3 import quat_to_r9, rotate_quat_by_rotvec

_LM_START = 1e-4
_LM_GIVE_UP = 1e12


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
    (linearise): L(guess), Lambda(guess) (contiguous), its Gram matrix and that matrix's
    Cholesky factor (upper triangle; None where singular).  A control cycle computes it
    while the measured lengths are on their way; they then enter only through
    Lambda^T (L - l)."""

    guess: Pose
    lengths: np.ndarray
    jacobian: np.ndarray
    gram: np.ndarray
    factor: np.ndarray | None


def linearise(geometry: CableGeometry, guess: Pose) -> Linearisation:
    """The measurement-free part of Y(l)'s first evaluation at `guess` (Linearisation)."""
    q = guess.quaternion_tuple
    table = to_array(geometry.evaluate(guess.position_tuple, quat_to_r9(*q)))
    table = table.reshape(geometry.n, 7)
    J = np.ascontiguousarray(table[:, :6])
    gram = J.T.dot(J)  # ndarray.dot: see the cdpr.kinematics docstring
    factor, info = dpotrf(gram)
    return Linearisation(guess, table[:, 6].copy(), J, gram, None if info else factor)


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
    remaining error is of the order of the step squared.  Each evaluation forms the
    n x 7 table [Lambda | L - l] and its Gram matrix, which holds Lambda^T Lambda,
    Lambda^T e and |e|^2 at once.
    """
    start = None
    if type(guess) is Linearisation:
        start, guess = guess, guess.guess
    n = geometry.n
    measured = np.asarray(lengths, dtype=float).ravel()
    m = measured.tolist()
    if len(m) != n:
        raise ValueError(f"expected {n} cable lengths, got {len(m)}")
    # a NaN or inf among them; finite lengths sum to inf only when absurdly large, and
    # those fail the residual check
    if not math.isfinite(sum(m)):
        for k, length in enumerate(m):
            if not math.isfinite(length):
                reason = f"non-finite length {length} at cable {k}"
                return FKResult(guess, math.inf, 0, False, reason)
    evaluate = geometry.evaluate
    tolerance2 = settings.step_tolerance**2
    p = guess.position_tuple
    q = guess.quaternion_tuple
    # the linearisation at (p, q): Lambda, Lambda^T Lambda, Lambda^T e and |e|^2
    if start is None:
        table = to_array(evaluate(p, quat_to_r9(*q), measured=m)).reshape(n, 7)
        S = table.T.dot(table)  # ndarray.dot: see the cdpr.kinematics docstring
        J, gram, g, cost = table[:, :6], S[:6, :6], S[:6, 6], float(S[6, 6])
        factor = None
    else:
        e = start.lengths - measured
        J, gram, factor = start.jacobian, start.gram, start.factor
        g, cost = e.dot(J), float(e.dot(e))
    lam = 0.0
    for it in range(1, settings.max_iterations + 1):
        if factor is not None:  # the prepared linearisation's, undamped
            chol = factor
            x, info = dpotrs(chol, g)
            factor = None
        else:
            if lam:
                A = gram.copy()
                A[_DIAG] *= 1.0 + lam
            else:
                A = gram
            chol, x, info = dposv(A, g)
        if info != 0:  # singular normal equations: damp harder
            lam = max(lam * 10.0, _LM_START)
            if lam > _LM_GIVE_UP:
                reason = "singular Jacobian"
                return _result(p, q, cost, it, n, reason, settings, guess, J)
            continue
        dx, dy, dz, wx, wy, wz = x.tolist()
        step2 = _longer2(dx * dx + dy * dy + dz * dz, wx * wx + wy * wy + wz * wz)
        p_new = [p[0] - dx, p[1] - dy, p[2] - dz]
        q_new = rotate_quat_by_rotvec(q, -wx, -wy, -wz)
        if not lam and step2 < tolerance2:
            # linearised cost after the step: |e|^2 - g . A^-1 g
            cost_new = cost - float(g.dot(x))
            return _result(p_new, q_new, cost_new, it, n, "", settings, guess, J, chol)
        if not lam and step2 < _CHORD_BELOW2:
            # quadratic regime: one more step with this factorisation and Jacobian needs
            # only the lengths; its error is ~ step x next step, far below tolerance
            done = _chord_finish(geometry, m, p_new, q_new, J, chol, tolerance2)
            if done is not None:
                p_new, q_new, chord_cost = done
                return _result(p_new, q_new, chord_cost, it + 1, n, "", settings, guess, J, chol)
        table = to_array(evaluate(p_new, quat_to_r9(*q_new), measured=m)).reshape(n, 7)
        S_new = table.T.dot(table)
        cost_new = float(S_new[6, 6])
        if cost_new <= cost or not math.isfinite(cost):
            p, q, cost = p_new, q_new, cost_new
            J, gram, g = table[:, :6], S_new[:6, :6], S_new[:6, 6]
            lam = lam * 0.1 if lam > _LM_START else 0.0
            if step2 < tolerance2:
                return _result(p, q, cost, it, n, "", settings, guess, J)
        else:
            lam = max(lam * 10.0, _LM_START)
            if lam > _LM_GIVE_UP:
                reason = "no descent direction"
                return _result(p, q, cost, it, n, reason, settings, guess, J)
    reason = f"no convergence in {settings.max_iterations} iterations"
    iterations = settings.max_iterations
    return _result(p, q, cost, iterations, n, reason, settings, guess, J)


def _chord_finish(
    geometry: CableGeometry,
    meas: list[float],
    p: list[float],
    q: tuple[float, float, float, float],
    jacobian: np.ndarray,
    chol: np.ndarray,
    tolerance2: float,
) -> tuple[list[float], tuple[float, float, float, float], float] | None:
    """A simplified-Newton step reusing the last Jacobian (Lambda of the last
    linearisation) and its Cholesky factor.  Returns the final (p, q, linearised
    cost), or None if the step is not yet short (tolerance2 is the squared step
    tolerance)."""
    residuals = geometry.evaluate(p, quat_to_r9(*q), jacobian=False, measured=meas)
    g = np.array(residuals).dot(jacobian)  # Lambda^T e
    x, info = dpotrs(chol, g)
    if info != 0:
        return None
    dx, dy, dz, wx, wy, wz = x.tolist()
    if _longer2(dx * dx + dy * dy + dz * dz, wx * wx + wy * wy + wz * wz) >= tolerance2:
        return None
    p_new = [p[0] - dx, p[1] - dy, p[2] - dz]
    q_new = rotate_quat_by_rotvec(q, -wx, -wy, -wz)
    return p_new, q_new, sum([r * r for r in residuals]) - float(g.dot(x))


_CHORD_BELOW2 = 1e-4**2  # squared step length below which the chord finish is tried


def _longer2(translation2: float, rotation2: float) -> float:
    """The squared step length, max(|dp|^2, |dw|^2) (builtin max is slower for 2 floats)."""
    return translation2 if translation2 > rotation2 else rotation2


_DIAG = np.diag_indices(6)


def _result(
    p: Sequence[float],
    q: tuple[float, float, float, float],
    cost: float,
    iterations: int,
    n: int,
    reason: str,
    settings: FKSettings,
    fallback: Pose,
    jacobian: np.ndarray,
    factor: np.ndarray | None = None,
) -> FKResult:
    """The FKResult.  `factor` is the Cholesky factor of the normal equations of
    `jacobian` when the caller has it (an undamped last step), else it is computed here."""
    residual = math.sqrt(max(cost, 0.0) / n) if math.isfinite(cost) else math.inf
    if not (math.isfinite(sum(p)) and math.isfinite(sum(q))):
        return FKResult(fallback, math.inf, iterations, False, "diverged to non-finite values")
    if not reason and residual > settings.max_residual:
        reason = (
            f"length residual {residual:.3g} m exceeds max_residual {settings.max_residual:.3g} m"
        )
    if reason:
        return FKResult(Pose._from_unit(p, q), residual, iterations, False, reason)
    if factor is None:
        factor, info = dpotrf(jacobian.T @ jacobian)
        factor = None if info else factor
    return FKResult(Pose._from_unit(p, q), residual, iterations, True, "", jacobian, factor)
