"""The platform's M_p, mu_p compiled (numba), and the wrench screen of many samples that
numpy would spend in per-call overhead (a trajectory validation's batches,
cdpr.wrench_check: ~1 ms of numpy calls a batch whatever its size, against a few
microseconds here).

The same maths as cdpr.dynamics and the numpy reference (cdpr.reference), which the
tests hold it equal to; the cables' part is cdpr.kinematics' kernel (its `rows`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.compiled_linalg import cholesky, cholesky_solve, gram
from cdpr.friction import SPEED_FLOOR
from cdpr.kinematics import cable_rows, rotation

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]


@njit(cache=True)
def platform_rows(platform: Array, R: Array, phi: Array, out: Array) -> None:
    """out (6, 7) = [M_p | mu_p] at rotation R and twist phi (cdpr.dynamics; `platform`
    is PlatformInertia.rows)."""
    m = platform[0]
    cx = R[0, 0] * platform[1] + R[0, 1] * platform[2] + R[0, 2] * platform[3]
    cy = R[1, 0] * platform[1] + R[1, 1] * platform[2] + R[1, 2] * platform[3]
    cz = R[2, 0] * platform[1] + R[2, 1] * platform[2] + R[2, 2] * platform[3]
    I_p = np.zeros((3, 3))  # R I_pb R^T
    for i in range(3):
        for j in range(3):
            s = 0.0
            for a in range(3):
                for b in range(3):
                    s += R[i, a] * platform[4 + 3 * a + b] * R[j, b]
            I_p[i, j] = s
    gx, gy, gz = platform[13], platform[14], platform[15]
    wx, wy, wz = phi[3], phi[4], phi[5]
    # a = w x (w x c) - g: the acceleration of the CoM relative to p, and gravity
    vx, vy, vz = wy * cz - wz * cy, wz * cx - wx * cz, wx * cy - wy * cx
    ax = wy * vz - wz * vy - gx
    ay = wz * vx - wx * vz - gy
    az = wx * vy - wy * vx - gz
    hx = I_p[0, 0] * wx + I_p[0, 1] * wy + I_p[0, 2] * wz
    hy = I_p[1, 0] * wx + I_p[1, 1] * wy + I_p[1, 2] * wz
    hz = I_p[2, 0] * wx + I_p[2, 1] * wy + I_p[2, 2] * wz
    mcx, mcy, mcz = m * cx, m * cy, m * cz
    out[:, :] = 0.0
    for i in range(3):
        out[i, i] = m
        for j in range(3):
            out[3 + i, 3 + j] = I_p[i, j]
    out[0, 4], out[0, 5], out[1, 3], out[1, 5], out[2, 3], out[2, 4] = (
        mcz, -mcy, -mcz, mcx, mcy, -mcx,
    )  # fmt: skip
    out[3, 1], out[3, 2], out[4, 0], out[4, 2], out[5, 0], out[5, 1] = (
        -mcz, mcy, mcz, -mcx, -mcy, mcx,
    )  # fmt: skip
    out[0, 6], out[1, 6], out[2, 6] = m * ax, m * ay, m * az
    out[3, 6] = wy * hz - wz * hy + mcz * gy - mcy * gz
    out[4, 6] = wz * hx - wx * hz + mcx * gz - mcz * gx
    out[5, 6] = wx * hy - wy * hx + mcy * gx - mcx * gy


@njit(cache=True)
def model_rows(
    cables: Array,
    platform: Array,
    m0: Array,
    p: tuple[float, float, float],
    q: tuple[float, float, float, float],
    phi: tuple[float, ...],
    table: Array,
    G: Array,
) -> None:
    """At position p, unit quaternion q and twist phi: table (n, 7) = [Lambda | c] and
    G (7, 7) = [Lambda | c]^T diag(m0) [Lambda | c] plus [M_p | mu_p] in its first 6
    rows, so that G[:6, :6] = M and G[:6, 6] = mu (cdpr.robot.Robot.model_terms)."""
    n = cables.shape[0]
    R, lengths, Mp = np.empty((3, 3)), np.empty(n), np.empty((6, 7))
    rotation(q, R)
    cable_rows(cables, p, R, phi, table, lengths)
    platform_rows(platform, R, phi, Mp)
    for a in range(7):
        for b in range(a + 1):
            s = 0.0
            for k in range(n):
                s += m0[k] * table[k, a] * table[k, b]
            G[a, b] = s
            G[b, a] = s
    for i in range(6):
        for j in range(7):
            G[i, j] += Mp[i, j]


@njit(cache=True)
def wrench_screen(
    positions: Array,
    rotations: Array,
    twists: Array,
    accels: Array,
    cables: Array,
    platform: Array,
    actuators: Array,
    margin: float,
    clear: NDArray[np.bool_],
    lengths: Array,
    jacobians: Array,
) -> None:
    """For each sample (positions N x 3, rotations N x 3 x 3, twists and accels N x 6):
    clear[s] when the least-norm tensions about t_ref that give the wrench the platform
    needs lie inside their bounds at t_min (cdpr.tension: t_lo = max(t_min, f0 + f_b -
    force_max), t_hi = f0 + f_b + force_max) by `margin` (N) and carry it to within
    `margin`; also the cable lengths (N x n) and Lambda (N x n x 6).  `actuators` (6, n):
    rows m0, k0, friction, t_min, force_max, t_ref.

    The wrench the tensions must give, w = Lambda^T f0 - tau with tau = M alpha + mu and
    f0 = m0 (Lambda alpha + c), is -(M_p alpha + mu_p): the drums' inertia is in f0."""
    n = cables.shape[0]
    m0, k0, friction = actuators[0], actuators[1], actuators[2]
    t_min, f_max, t_ref = actuators[3], actuators[4], actuators[5]
    table = np.empty((n, 7))
    Mp = np.empty((6, 7))
    G = np.empty((6, 6))
    L = np.zeros((6, 6))
    w = np.empty(6)
    x = np.empty(6)
    t = np.empty(n)
    for s in range(positions.shape[0]):
        phi, alpha = twists[s], accels[s]
        cable_rows(cables, positions[s], rotations[s], phi, table, lengths[s])
        platform_rows(platform, rotations[s], phi, Mp)
        jacobians[s] = table[:, :6]
        for i in range(6):
            acc = Mp[i, 6]
            for j in range(6):
                acc += Mp[i, j] * alpha[j]
            w[i] = -acc
        # x = (Lambda^T Lambda)^-1 (w - Lambda^T t_ref), the least-norm tensions t_ref + Lambda x
        for a in range(6):
            acc = w[a]
            for k in range(n):
                acc -= table[k, a] * t_ref[k]
            x[a] = acc
        gram(table[:, :6].T, G)
        if not cholesky(G, L):
            clear[s] = False
            continue
        cholesky_solve(L, x)
        inside = True
        for k in range(n):
            tension, rate, la = t_ref[k], 0.0, table[k, 6]
            for j in range(6):
                tension += table[k, j] * x[j]
                rate += table[k, j] * phi[j]
                la += table[k, j] * alpha[j]
            t[k] = tension
            g = m0[k] * la + k0[k] * rate + friction[k] * math.tanh(rate / SPEED_FLOOR)
            low = max(t_min[k], g - f_max[k])
            inside &= low + margin <= tension <= g + f_max[k] - margin
        for a in range(6):
            acc = -w[a]
            for k in range(n):
                acc += table[k, a] * t[k]
            inside &= abs(acc) <= margin
        clear[s] = inside
