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
from numpy.typing import ArrayLike
from scipy.linalg.lapack import dposv, dpotrs

from cdpr.kinematics import CableGeometry
from cdpr.pose import Pose
from cdpr.so3 import quat_to_r9, rotate_quat_by_rotvec

_LM_START = 1e-4
_LM_GIVE_UP = 1e12


class FKResult(NamedTuple):
    """Outcome of Y(l): the pose, RMS length residual (m), iterations, and why not converged.

    `jacobian` is Lambda at the solver's last linearisation point, less than one step
    tolerance-scale step (<= 1e-4 m / rad) from `pose` when converged: accurate enough
    for the least-squares twist of the same cycle, and free.
    """

    pose: Pose
    residual: float
    iterations: int
    converged: bool
    reason: str = ""
    jacobian: np.ndarray | None = None


@dataclass(frozen=True)
class FKSettings:
    max_iterations: int = 50
    step_tolerance: float = 1e-8
    max_residual: float = 2e-3


def solve_forward_kinematics(
    geometry: CableGeometry, lengths: ArrayLike, guess: Pose, settings: FKSettings
) -> FKResult:
    """Pose whose cable lengths best match `lengths` (least squares), started at `guess`.

    Gauss-Newton while it reduces the cost, Levenberg-Marquardt damping when a step
    does not.  A Gauss-Newton step shorter than step_tolerance (m, or rad) ends the
    iteration without a further evaluation: convergence is quadratic there, so the
    remaining error is of the order of the step squared.  Each evaluation forms the
    n x 7 table [Lambda | L - l] and its Gram matrix, which holds Lambda^T Lambda,
    Lambda^T e and |e|^2 at once.
    """
    n = geometry.n
    meas = np.asarray(lengths, dtype=float).reshape(-1)
    if meas.shape[0] != n:
        raise ValueError(f"expected {n} cable lengths, got {meas.shape[0]}")
    if not math.isfinite(meas @ meas):
        k = int(np.flatnonzero(~np.isfinite(meas))[0])
        return FKResult(guess, math.inf, 0, False, f"non-finite length {meas[k]} at cable {k}")
    evaluate = geometry.evaluate
    tolerance2 = settings.step_tolerance**2
    m = meas.tolist()
    p = guess.position.tolist()
    q = tuple(guess.quaternion.tolist())
    table = np.array(evaluate(p, quat_to_r9(*q), measured=m)).reshape(n, 7)
    S = table.T @ table
    cost = float(S[6, 6])
    lam = 0.0
    for it in range(1, settings.max_iterations + 1):
        if lam:
            A = S[:6, :6].copy()
            A[_DIAG] *= 1.0 + lam
        else:
            A = S[:6, :6]
        g = S[:6, 6]
        chol, x, info = dposv(A, g)
        if info != 0:  # singular normal equations: damp harder
            lam = max(lam * 10.0, _LM_START)
            if lam > _LM_GIVE_UP:
                return _result(p, q, cost, it, n, "singular Jacobian", settings, guess, table)
            continue
        dx, dy, dz, wx, wy, wz = x.tolist()
        step2 = max(dx * dx + dy * dy + dz * dz, wx * wx + wy * wy + wz * wz)  # squared
        p_new = [p[0] - dx, p[1] - dy, p[2] - dz]
        q_new = rotate_quat_by_rotvec(q, -wx, -wy, -wz)
        if not lam and step2 < tolerance2:
            # linearised cost after the step: |e|^2 - g . A^-1 g
            cost_new = cost - float(g @ x)
            return _result(p_new, q_new, cost_new, it, n, "", settings, guess, table)
        if not lam and step2 < _CHORD_BELOW2:
            # quadratic regime: one more step with this factorisation and Jacobian needs
            # only the lengths; its error is ~ step x next step, far below tolerance
            done = _chord_finish(geometry, m, p_new, q_new, table[:, :6], chol, tolerance2)
            if done is not None:
                p_new, q_new, chord_cost = done
                return _result(p_new, q_new, chord_cost, it + 1, n, "", settings, guess, table)
        table = np.array(evaluate(p_new, quat_to_r9(*q_new), measured=m)).reshape(n, 7)
        S_new = table.T @ table
        cost_new = float(S_new[6, 6])
        if cost_new <= cost or not math.isfinite(cost):
            p, q, S, cost = p_new, q_new, S_new, cost_new
            lam = lam * 0.1 if lam > _LM_START else 0.0
            if step2 < tolerance2:
                return _result(p, q, cost, it, n, "", settings, guess, table)
        else:
            lam = max(lam * 10.0, _LM_START)
            if lam > _LM_GIVE_UP:
                reason = "no descent direction"
                return _result(p, q, cost, it, n, reason, settings, guess, table)
    reason = f"no convergence in {settings.max_iterations} iterations"
    return _result(p, q, cost, settings.max_iterations, n, reason, settings, guess, table)


def _chord_finish(
    geometry: CableGeometry,
    meas: list[float],
    p: list[float],
    q: tuple[float, float, float, float],
    J: np.ndarray,
    chol: np.ndarray,
    tolerance2: float,
) -> tuple[list[float], tuple[float, float, float, float], float] | None:
    """A simplified-Newton step reusing the last Jacobian and its Cholesky factor.
    Returns the final (p, q, linearised cost), or None if the step is not yet short
    (tolerance2 is the squared step tolerance)."""
    e = np.array(geometry.evaluate(p, quat_to_r9(*q), jacobian=False, measured=meas))
    g = J.T @ e
    x, info = dpotrs(chol, g)
    if info != 0:
        return None
    dx, dy, dz, wx, wy, wz = x.tolist()
    if max(dx * dx + dy * dy + dz * dz, wx * wx + wy * wy + wz * wz) >= tolerance2:
        return None
    p_new = [p[0] - dx, p[1] - dy, p[2] - dz]
    q_new = rotate_quat_by_rotvec(q, -wx, -wy, -wz)
    return p_new, q_new, float(e @ e) - float(g @ x)


_CHORD_BELOW2 = 1e-4**2  # squared step length below which the chord finish is tried
_DIAG = np.diag_indices(6)


def _result(
    p: list[float],
    q: tuple[float, float, float, float],
    cost: float,
    iterations: int,
    n: int,
    reason: str,
    settings: FKSettings,
    fallback: Pose,
    table: np.ndarray,
) -> FKResult:
    residual = math.sqrt(max(cost, 0.0) / n) if math.isfinite(cost) else math.inf
    if not (math.isfinite(sum(p)) and math.isfinite(sum(q))):
        return FKResult(fallback, math.inf, iterations, False, "diverged to non-finite values")
    if not reason and residual > settings.max_residual:
        reason = (
            f"length residual {residual:.3g} m exceeds max_residual {settings.max_residual:.3g} m"
        )
    jacobian = None if reason else table[:, :6]
    return FKResult(Pose._from_unit(p, q), residual, iterations, not reason, reason, jacobian)
