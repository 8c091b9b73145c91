"""Cable kinematics: L(eta), Lambda(eta) and c(eta, phi), compiled (numba).

Conventions (DESIGN §3): d_k = p + R b_k - a_k, l_k = |d_k|, u_k = d_k / l_k,
Lambda row k = [u_k, r_k x u_k] with r_k = R b_k, so l_dot = Lambda phi, and
l_ddot = Lambda alpha + c(eta, phi).

With the standard pulley model the cable runs along the pulley's swivel axis z into
the pulley at the anchor point, wraps an angle beta around it and leaves tangentially
at P towards the attachment B: l = r_p beta + |B - P|, and u is the direction of the
free segment.  The Hessian of l in B is n_P n_P^T / l_free (in the pulley plane, n_P
the pulley radius direction at P) plus (u . x_p / rho) n n^T across it (rho the
distance of B from the swivel axis), which gives c.

One implementation, compiled, for the control cycle (forward kinematics, the model
terms), the simulator's plant and the validation's batches alike: for 8 cables a call
costs ~1 us against ~7 us for the same loop in scalar Python, whose per-float work and
numpy's per-call overhead dominated the cycle at this size.  The kernels are loaded
from numba's cache (cdpr.compiled_cache) when a robot is built, before any cycle runs.
A readable numpy reference lives in cdpr.reference and the tests hold the two equal.

Around the kernels the hot paths (the controller, the tension distribution) multiply
small arrays with ndarray.dot, which costs about half of the @ operator's matmul-ufunc
dispatch, and keep operands contiguous (a product copies a strided operand every time).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cdpr.compiled_cache import key_numba_cache
from cdpr.so3 import quat_to_r9

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]
_r9 = njit(cache=True)(quat_to_r9)  # the same function, callable from the kernels
AT_REST = (0.0,) * 6


class CableGeometry:
    """Anchors a_k (world), attachments b_k (platform frame), optional pulleys.

    `rows` (n, 10) is what the kernels take: per cable [a_k, b_k, pulley radius (0:
    none), pulley swivel axis]."""

    def __init__(
        self,
        anchors: NDArray[np.float64],
        attachments: NDArray[np.float64],
        pulleys: Sequence[tuple[float, tuple[float, float, float]] | None],
    ) -> None:
        self.anchors = np.array(anchors, dtype=float)
        self.attachments = np.array(attachments, dtype=float)
        self.pulleys = list(pulleys)
        self.n = len(self.anchors)
        rows = np.zeros((self.n, 10))
        rows[:, :3] = self.anchors
        rows[:, 3:6] = self.attachments
        for k, pulley in enumerate(self.pulleys):
            if pulley is not None:
                rows[k, 6] = pulley[0]
                rows[k, 7:] = pulley[1]
        self.rows = rows

    def table(
        self,
        position: tuple[float, float, float],
        quaternion: tuple[float, float, float, float],
        twist: tuple[float, ...] = AT_REST,
    ) -> tuple[Array, Array]:
        """At a pose (position, unit quaternion (w, x, y, z), tuples of floats) moving
        with `twist` (6 floats, a tuple): the n x 7 table [Lambda | c] and the lengths."""
        table = np.empty((self.n, 7))
        lengths = np.empty(self.n)
        pose_rows(self.rows, position, quaternion, twist, table, lengths)
        return table, lengths


@njit(cache=True)
def rotation(q: tuple[float, float, float, float], R: Array) -> None:
    """R (3, 3) = the rotation matrix of the unit quaternion q (cdpr.so3.quat_to_r9)."""
    m = _r9(q[0], q[1], q[2], q[3])
    R[0, 0], R[0, 1], R[0, 2] = m[0], m[1], m[2]
    R[1, 0], R[1, 1], R[1, 2] = m[3], m[4], m[5]
    R[2, 0], R[2, 1], R[2, 2] = m[6], m[7], m[8]


@njit(cache=True)
def pose_rows(
    cables: Array,
    p: tuple[float, float, float],
    q: tuple[float, float, float, float],
    phi: tuple[float, ...],
    table: Array,
    lengths: Array,
) -> None:
    """cable_rows at position p and unit quaternion q."""
    R = np.empty((3, 3))
    rotation(q, R)
    cable_rows(cables, p, R, phi, table, lengths)


@njit(cache=True)
def cable_rows(cables: Array, p: Array, R: Array, phi: Array, table: Array, lengths: Array) -> None:
    """At position p (3,), rotation R (3, 3) and twist phi (6,): table (n, 7) rows
    [u_k, r_k x u_k, c_k] (Lambda and c) and lengths (n,) (the module docstring)."""
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
    """(length, u, xd^T H xd) of a cable over its pulley, d = B - a: the wrap arc and
    the free segment, and the Hessian term of the module docstring."""
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
