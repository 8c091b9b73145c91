"""The model compiled (numba): cable lengths, Lambda, c and the platform's M_p, mu_p at
a pose, for loops over many samples that numpy would spend in per-call overhead (a
trajectory validation's screen, cdpr.wrench_check: ~1 ms of numpy calls a batch
whatever its size, against a few microseconds here).

The same maths as the scalar hot path (cdpr.kinematics, cdpr.dynamics) and the numpy
reference (cdpr.reference), which the tests hold it equal to.  The cables come as one
array (`cable_array`): per row the anchor a_k, the attachment b_k, the pulley radius
(0: none) and its swivel axis.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.dynamics import PlatformInertia
from cdpr.friction import SPEED_FLOOR
from cdpr.kinematics import CableGeometry
from cdpr.wrench_margin import _cholesky, _gram, _solve

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]


def cable_array(geometry: CableGeometry) -> Array:
    """(n, 10) rows [a_k, b_k, pulley radius (0: none), pulley axis] for the kernels."""
    rows = np.zeros((geometry.n, 10))
    rows[:, :3] = geometry.anchors
    rows[:, 3:6] = geometry.attachments
    for k, pulley in enumerate(geometry.pulleys):
        if pulley is not None:
            rows[k, 6] = pulley[0]
            rows[k, 7:] = pulley[1]
    return rows


def platform_array(platform: PlatformInertia) -> Array:
    """(16,) [m, c_b, I_pb row-major, g] for platform_rows."""
    return np.array(
        [platform.mass, *platform.center_of_mass, *platform.inertia_about_p, *platform.gravity]
    )


@njit(cache=True)
def cable_rows(cables: Array, p: Array, R: Array, phi: Array, table: Array, lengths: Array) -> None:
    """At position p (3,), rotation R (3, 3) and twist phi (6,): table (n, 7) rows
    [u_k, r_k x u_k, c_k] (Lambda and c) and lengths (n,) (cdpr.kinematics)."""
    vx, vy, vz, wx, wy, wz = phi[0], phi[1], phi[2], phi[3], phi[4], phi[5]
    for k in range(cables.shape[0]):
        bx, by, bz = cables[k, 3], cables[k, 4], cables[k, 5]
        rx = R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz
        ry = R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz
        rz = R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz
        dx = p[0] + rx - cables[k, 0]
        dy = p[1] + ry - cables[k, 1]
        dz = p[2] + rz - cables[k, 2]
        # attachment velocity xd = v + w x r, centripetal acceleration w x (w x r)
        wrx = wy * rz - wz * ry
        wry = wz * rx - wx * rz
        wrz = wx * ry - wy * rx
        xdx, xdy, xdz = vx + wrx, vy + wry, vz + wrz
        rp = cables[k, 6]
        if rp == 0.0:
            length = math.sqrt(dx * dx + dy * dy + dz * dz)
            inv = 1.0 / length
            ux, uy, uz = dx * inv, dy * inv, dz * inv
            ud = ux * xdx + uy * xdy + uz * xdz
            quad = (xdx * xdx + xdy * xdy + xdz * xdz - ud * ud) * inv
        else:
            length, ux, uy, uz, quad = _pulley(cables[k], dx, dy, dz, xdx, xdy, xdz)
        centripetal = ux * (wy * wrz - wz * wry) + uy * (wz * wrx - wx * wrz)
        centripetal += uz * (wx * wry - wy * wrx)
        table[k, 0], table[k, 1], table[k, 2] = ux, uy, uz
        table[k, 3] = ry * uz - rz * uy
        table[k, 4] = rz * ux - rx * uz
        table[k, 5] = rx * uy - ry * ux
        table[k, 6] = centripetal + quad
        lengths[k] = length


@njit(cache=True)
def _pulley(
    cable: Array, dx: float, dy: float, dz: float, xdx: float, xdy: float, xdz: float
) -> tuple[float, float, float, float, float]:
    """(length, u, xd^T H xd) of a cable over its pulley, d = B - a (cdpr.kinematics'
    pulley_length_direction and pulley_curvature)."""
    rp, zx, zy, zz = cable[6], cable[7], cable[8], cable[9]
    along = dx * zx + dy * zy + dz * zz
    ex, ey, ez = dx - along * zx, dy - along * zy, dz - along * zz
    rho = math.sqrt(ex * ex + ey * ey + ez * ez)
    if rho < 1e-12:  # B on the swivel axis: any perpendicular direction
        ax, ay, az = (1.0, 0.0, 0.0) if abs(zx) < 0.9 else (0.0, 1.0, 0.0)
        dot = ax * zx + ay * zy + az * zz
        ax, ay, az = ax - dot * zx, ay - dot * zy, az - dot * zz
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        xx, xy, xz = ax / norm, ay / norm, az / norm
        rho = 1e-12
    else:
        xx, xy, xz = ex / rho, ey / rho, ez / rho
    wx_, wz_ = rho - rp, along
    wnorm = math.sqrt(wx_ * wx_ + wz_ * wz_)
    free = math.sqrt(max(wnorm * wnorm - rp * rp, 0.0))
    theta_p = math.atan2(wz_, wx_) + math.acos(min(1.0, rp / wnorm))
    s, c = math.sin(theta_p), math.cos(theta_p)
    length = rp * (math.pi - theta_p) + free
    ux, uy, uz = s * xx - c * zx, s * xy - c * zy, s * xz - c * zz
    # the radial direction at the leave point, and the normal of the pulley plane
    npx, npy, npz = c * xx + s * zx, c * xy + s * zy, c * xz + s * zz
    nx, ny, nz = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    a = npx * xdx + npy * xdy + npz * xdz
    b = nx * xdx + ny * xdy + nz * xdz
    quad = a * a / free + (ux * xx + uy * xy + uz * xz) / rho * b * b
    return length, ux, uy, uz, quad


@njit(cache=True)
def platform_rows(platform: Array, R: Array, phi: Array, out: Array) -> None:
    """out (6, 7) = [M_p | mu_p] at rotation R and twist phi (cdpr.dynamics)."""
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
        _gram(table[:, :6].T, G)
        if not _cholesky(G, L):
            clear[s] = False
            continue
        _solve(L, x)
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
