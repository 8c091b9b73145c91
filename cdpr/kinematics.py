"""Cable kinematics on the hot path: L(eta), Lambda(eta) and c(eta, phi).

Conventions (DESIGN §3): d_k = p + R b_k - a_k, l_k = |d_k|, u_k = d_k / l_k,
Lambda row k = [u_k, r_k x u_k] with r_k = R b_k, so l_dot = Lambda phi, and
l_ddot = Lambda alpha + c(eta, phi).

With the standard pulley model the cable runs along the pulley's swivel axis z into
the pulley at the anchor point, wraps an angle beta around it and leaves tangentially
at P towards the attachment B: l = r_p beta + |B - P|, and u is the direction of the
free segment.  The Hessian of l in B is n_P n_P^T / l_free (in the pulley plane, n_P
the pulley radius direction at P) plus (u . x_p / rho) n n^T across it (rho the
distance of B from the swivel axis), which gives c.

This is scalar Python on floats: for 6-12 cables it is several times faster than
numpy, whose per-call overhead dominates at this size (see PERF-FACTS).  A readable
numpy reference lives in cdpr.reference and the tests hold the two equal.  For the same
reason the hot paths elsewhere (forward kinematics, the controller, the tension
distribution) multiply small arrays with ndarray.dot, which costs about half of the @
operator's matmul-ufunc dispatch, and keep operands contiguous (a product copies a
strided operand every time).
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

Matrix9 = Sequence[float]  # row-major rotation matrix as 9 floats


def to_array(values: list[float]) -> NDArray[np.float64]:
    """np.array(values) for a list of floats, such as the table CableGeometry.evaluate
    returns: struct packs the floats in one C loop and numpy views the (writable) bytes,
    half the cost of np.array or np.fromiter, whose per-element conversion is generic
    (it dominates for the 56-entry tables of the hot path)."""
    return np.frombuffer(bytearray(_packer(len(values))(*values)))


@functools.cache
def _packer(count: int) -> Callable[..., bytes]:
    return struct.Struct(f"{count}d").pack


class CableGeometry:
    """Anchors a_k (world), attachments b_k (platform frame), optional pulleys."""

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
        self._cables = [
            (*map(float, a), *map(float, b), None if pl is None else (float(pl[0]), *pl[1]))
            for a, b, pl in zip(self.anchors, self.attachments, self.pulleys, strict=True)
        ]
        self._zeros = (0.0,) * self.n

    def evaluate(
        self,
        p: Sequence[float],
        R: Matrix9,
        phi: Sequence[float] | None = None,
        jacobian: bool = True,
        measured: Sequence[float] | None = None,
    ) -> list[float]:
        """One flat list, per cable [u, r x u, last] (stride 7), whose last entry is:
        the length l, or l - measured when `measured` is given, or c when the twist phi
        is given.  With jacobian=False only the last entries.  Flat, so that one numpy
        call turns it into an n x 7 table whose Gram matrix holds the FK normal
        equations (or, weighted by m0, Lambda^T D Lambda and Lambda^T D c)."""
        px, py, pz = p
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
        if phi is not None:
            vx, vy, vz, wx, wy, wz = phi
        table: list[float] = []
        for (ax, ay, az, bx, by, bz, pulley), ref in zip(
            self._cables, self._zeros if measured is None else measured, strict=True
        ):
            rx = r00 * bx + r01 * by + r02 * bz
            ry = r10 * bx + r11 * by + r12 * bz
            rz = r20 * bx + r21 * by + r22 * bz
            dx = px + rx - ax
            dy = py + ry - ay
            dz = pz + rz - az
            if pulley is None:
                length = math.sqrt(dx * dx + dy * dy + dz * dz)
                inv = 1.0 / length
                ux = dx * inv
                uy = dy * inv
                uz = dz * inv
            else:
                length, ux, uy, uz, pframe = pulley_length_direction(dx, dy, dz, pulley)
            if phi is None:
                last = length - ref
            else:
                # attachment velocity xd = v + w x r, centripetal acceleration w x (w x r)
                wrx = wy * rz - wz * ry
                wry = wz * rx - wx * rz
                wrz = wx * ry - wy * rx
                xdx = vx + wrx
                xdy = vy + wry
                xdz = vz + wrz
                centripetal = (
                    ux * (wy * wrz - wz * wry)
                    + uy * (wz * wrx - wx * wrz)
                    + uz * (wx * wry - wy * wrx)
                )
                if pulley is None:
                    ud = ux * xdx + uy * xdy + uz * xdz
                    quad = (xdx * xdx + xdy * xdy + xdz * xdz - ud * ud) * inv
                else:
                    quad = pulley_curvature(pframe, ux, uy, uz, xdx, xdy, xdz)
                last = centripetal + quad
            if jacobian:  # the whole row in one extend
                table += (ux, uy, uz, ry * uz - rz * uy, rz * ux - rx * uz, rx * uy - ry * ux, last)
            else:
                table.append(last)
        return table


def _pulley_frame(
    dx: float, dy: float, dz: float, pulley: tuple[float, float, float, float]
) -> tuple[float, ...]:
    """Pulley plane geometry for d = B - a: (rp, z, x_p, rho, theta_p, free length) with
    x_p the unit direction from the swivel axis towards B, rho the distance of B from
    the axis, and theta_p the angle of the leave point P in the (x_p, z) plane."""
    rp, zx, zy, zz = pulley
    dz_ax = dx * zx + dy * zy + dz * zz
    ex = dx - dz_ax * zx
    ey = dy - dz_ax * zy
    ez = dz - dz_ax * zz
    rho = math.sqrt(ex * ex + ey * ey + ez * ez)
    if rho < 1e-12:  # B on the swivel axis: the swivel angle is undefined; pick one
        xx, xy, xz = _any_perpendicular(zx, zy, zz)
        rho = 1e-12
    else:
        xx, xy, xz = ex / rho, ey / rho, ez / rho
    wx_ = rho - rp
    wz_ = dz_ax
    wnorm = math.sqrt(wx_ * wx_ + wz_ * wz_)
    free = math.sqrt(max(wnorm * wnorm - rp * rp, 0.0))
    theta_p = math.atan2(wz_, wx_) + math.acos(min(1.0, rp / wnorm))
    return rp, zx, zy, zz, xx, xy, xz, rho, theta_p, free


def pulley_length_direction(
    dx: float, dy: float, dz: float, pulley: tuple[float, float, float, float]
) -> tuple[float, float, float, float, tuple[float, ...]]:
    """Length (wrap arc + free segment), free-segment direction u, and the pulley
    frame that pulley_curvature needs."""
    frame = _pulley_frame(dx, dy, dz, pulley)
    rp, zx, zy, zz, xx, xy, xz, _rho, theta_p, free = frame
    s = math.sin(theta_p)
    c = math.cos(theta_p)
    length = rp * (math.pi - theta_p) + free
    return length, s * xx - c * zx, s * xy - c * zy, s * xz - c * zz, frame


def pulley_curvature(
    frame: tuple[float, ...], ux: float, uy: float, uz: float, xdx: float, xdy: float, xdz: float
) -> float:
    """The quadratic term xd^T H xd of a pulley cable's length in the attachment point."""
    _rp, zx, zy, zz, xx, xy, xz, rho, theta_p, free = frame
    s = math.sin(theta_p)
    c = math.cos(theta_p)
    # radial direction at the leave point, and the normal of the pulley plane
    npx, npy, npz = c * xx + s * zx, c * xy + s * zy, c * xz + s * zz
    nx, ny, nz = zy * xz - zz * xy, zz * xx - zx * xz, zx * xy - zy * xx
    a = npx * xdx + npy * xdy + npz * xdz
    b = nx * xdx + ny * xdy + nz * xdz
    return a * a / free + (ux * xx + uy * xy + uz * xz) / rho * b * b


def _any_perpendicular(zx: float, zy: float, zz: float) -> tuple[float, float, float]:
    """A unit vector perpendicular to the unit vector z."""
    ax, ay, az = (1.0, 0.0, 0.0) if abs(zx) < 0.9 else (0.0, 1.0, 0.0)
    dot = ax * zx + ay * zy + az * zz
    px, py, pz = ax - dot * zx, ay - dot * zy, az - dot * zz
    n = math.sqrt(px * px + py * py + pz * pz)
    return px / n, py / n, pz / n
