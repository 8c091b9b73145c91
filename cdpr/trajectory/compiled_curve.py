"""A curve's segments evaluated, compiled (numba): one sample (the real-time core's
reference, evaluate_segment in cdpr.trajectory.core) and Curve.sample_many's loop for
a validation's batches, where numpy spends ~1 ms of calls a batch (its rotation rates
alone ~50 calls) on what takes a few microseconds here.

The maths of rotate_quat_by_rotvec (cdpr.so3) and angular_rates (cdpr.trajectory.
rotation), with their series below the same thresholds; the tests hold them equal.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.so3 import _SMALL_ANGLE
from cdpr.trajectory.rotation import _SERIES, _SERIES_BELOW

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]
_SERIES_ROWS = np.array(_SERIES)  # Horner rows of (b, c, beta, gamma), highest power first


@njit(cache=True)
def evaluate_segments(
    tables: Array,
    quats: Array,
    segments: NDArray[np.intp],
    taus: Array,
    positions: Array,
    quaternions: Array,
    twists: Array,
    accels: Array,
) -> None:
    """Row i of the outputs: segment segments[i] (tables (m, 6, 18), start rotations
    quats (m, 4)) taus[i] seconds in: position, unit quaternion (w first), twist and
    accel."""
    y = np.empty(18)
    for i in range(taus.shape[0]):
        k = segments[i]
        q = quats[k]
        _evaluate(tables[k], q[0], q[1], q[2], q[3], taus[i], y,
                  positions[i], quaternions[i], twists[i], accels[i])  # fmt: skip


@njit(cache=True)
def segment_sample(
    table: Array, qw: float, qx: float, qy: float, qz: float, tau: float
) -> Array:
    """One sample of a segment (table (6, 18), start rotation (qw, qx, qy, qz)) tau
    seconds in, as 19 numbers: position, unit quaternion, twist, accel (the real-time
    core's reference, cdpr.trajectory.core.evaluate_segment)."""
    out = np.empty(19)
    _evaluate(table, qw, qx, qy, qz, tau, np.empty(18), out[:3], out[3:7], out[7:13], out[13:])
    return out


@njit(cache=True)
def _evaluate(
    table: Array,
    bw: float,
    bx: float,
    by: float,
    bz: float,
    tau: float,
    y: Array,
    position: Array,
    quaternion: Array,
    twist: Array,
    accel: Array,
) -> None:
    """A segment's sample tau seconds in (y: 18 numbers of scratch): the values, rates
    and accels of [p, theta] by one product of tau's powers with the table, the rotation
    exp(theta) q0 and the angular rates from theta's."""
    series = _SERIES_ROWS
    t2 = tau * tau
    t3 = t2 * tau
    powers = (1.0, tau, t2, t3, t3 * tau, t3 * t2)
    for j in range(18):
        acc = 0.0
        for r in range(6):
            acc += powers[r] * table[r, j]
        y[j] = acc
    position[0], position[1], position[2] = y[0], y[1], y[2]
    twist[0], twist[1], twist[2] = y[6], y[7], y[8]
    accel[0], accel[1], accel[2] = y[12], y[13], y[14]
    tx, ty, tz = y[3], y[4], y[5]
    # exp(theta) * q0, renormalised
    theta = math.sqrt(tx * tx + ty * ty + tz * tz)
    small = theta < _SMALL_ANGLE  # sin(theta/2) / theta by its series below
    s = 0.5 - theta * theta / 48.0 if small else math.sin(0.5 * theta) / theta
    aw, ax, ay, az = math.cos(0.5 * theta), s * tx, s * ty, s * tz
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    yq = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    norm = 1.0 / math.sqrt(w * w + x * x + yq * yq + z * z)
    quaternion[0], quaternion[1] = w * norm, x * norm
    quaternion[2], quaternion[3] = yq * norm, z * norm
    # omega = J_l theta_dot, omega_dot = J_l theta_ddot + (d/dt J_l) theta_dot
    x2 = theta * theta
    if x2 < _SERIES_BELOW:
        b = c = beta = gamma = 0.0
        for r in range(series.shape[0]):
            b = b * x2 + series[r, 0]
            c = c * x2 + series[r, 1]
            beta = beta * x2 + series[r, 2]
            gamma = gamma * x2 + series[r, 3]
    else:
        xs = math.sqrt(x2)
        sn, co = math.sin(xs), math.cos(xs)
        b = (1.0 - co) / x2
        c = (xs - sn) / (x2 * xs)
        beta = (xs * sn - 2.0 * (1.0 - co)) / (x2 * x2)
        gamma = (3.0 * sn - 2.0 * xs - xs * co) / (x2 * x2 * xs)
    dx, dy, dz = y[9], y[10], y[11]
    ex, ey, ez = y[15], y[16], y[17]
    ux, uy, uz = ty * dz - tz * dy, tz * dx - tx * dz, tx * dy - ty * dx
    wx, wy, wz = ty * uz - tz * uy, tz * ux - tx * uz, tx * uy - ty * ux
    fx, fy, fz = ty * ez - tz * ey, tz * ex - tx * ez, tx * ey - ty * ex
    gx, gy, gz = ty * fz - tz * fy, tz * fx - tx * fz, tx * fy - ty * fx
    kx, ky, kz = dy * uz - dz * uy, dz * ux - dx * uz, dx * uy - dy * ux
    sdot = tx * dx + ty * dy + tz * dz
    bs, gs = beta * sdot, gamma * sdot
    twist[3] = dx + b * ux + c * wx
    twist[4] = dy + b * uy + c * wy
    twist[5] = dz + b * uz + c * wz
    accel[3] = ex + b * fx + c * gx + bs * ux + gs * wx + c * kx
    accel[4] = ey + b * fy + c * gy + bs * uy + gs * wy + c * ky
    accel[5] = ez + b * fz + c * gz + bs * uz + gs * wz + c * kz
