"""A curve's segments evaluated at many times, compiled (numba): Curve.sample_many's
loop for a validation's batches, where numpy spends ~1 ms of calls a batch (its
rotation rates alone ~50 calls) on what takes a few microseconds here.

The same maths as evaluate_segment (cdpr.trajectory.core), rotate_quat_by_rotvec
(cdpr.so3) and angular_rates (cdpr.trajectory.rotation), with their series below the
same thresholds; the tests hold the two equal.  Imported where a batch is sampled, not
with the curve: the real-time core samples one time a cycle and loads no numba.
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
    series = _SERIES_ROWS
    for i in range(taus.shape[0]):
        k, tau = segments[i], taus[i]
        t2 = tau * tau
        t3 = t2 * tau
        powers = (1.0, tau, t2, t3, t3 * tau, t3 * t2)
        for j in range(18):
            acc = 0.0
            for r in range(6):
                acc += powers[r] * tables[k, r, j]
            y[j] = acc
        positions[i, 0], positions[i, 1], positions[i, 2] = y[0], y[1], y[2]
        twists[i, 0], twists[i, 1], twists[i, 2] = y[6], y[7], y[8]
        accels[i, 0], accels[i, 1], accels[i, 2] = y[12], y[13], y[14]
        tx, ty, tz = y[3], y[4], y[5]
        # exp(theta) * q0, renormalised
        theta = math.sqrt(tx * tx + ty * ty + tz * tz)
        small = theta < _SMALL_ANGLE  # sin(theta/2) / theta by its series below
        s = 0.5 - theta * theta / 48.0 if small else math.sin(0.5 * theta) / theta
        aw, ax, ay, az = math.cos(0.5 * theta), s * tx, s * ty, s * tz
        bw, bx, by, bz = quats[k, 0], quats[k, 1], quats[k, 2], quats[k, 3]
        w = aw * bw - ax * bx - ay * by - az * bz
        x = aw * bx + ax * bw + ay * bz - az * by
        yq = aw * by - ax * bz + ay * bw + az * bx
        z = aw * bz + ax * by - ay * bx + az * bw
        norm = 1.0 / math.sqrt(w * w + x * x + yq * yq + z * z)
        quaternions[i, 0], quaternions[i, 1] = w * norm, x * norm
        quaternions[i, 2], quaternions[i, 3] = yq * norm, z * norm
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
        twists[i, 3] = dx + b * ux + c * wx
        twists[i, 4] = dy + b * uy + c * wy
        twists[i, 5] = dz + b * uz + c * wz
        accels[i, 3] = ex + b * fx + c * gx + bs * ux + gs * wx + c * kx
        accels[i, 4] = ey + b * fy + c * gy + bs * uy + gs * wy + c * ky
        accels[i, 5] = ez + b * fz + c * gz + bs * uz + gs * wz + c * kz
