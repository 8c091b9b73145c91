"""Rotations: hat/vee, exp/log on SO(3), quaternion <-> matrix.

Quaternions are (w, x, y, z) arrays with the scalar first; they are returned
canonical (w >= 0) because q and -q are the same rotation.  exp and log are
accurate near 0 (series expansions) and near pi (log goes through a
quaternion built by Shepperd's method, then atan2, which stays well
conditioned where arccos((tr R - 1) / 2) does not).
"""

from __future__ import annotations

import math

import numpy as np
from numba.extending import register_jitable
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]

_SMALL_ANGLE = 1e-4  # below this, use Taylor series (error < 1e-17 relative)


def hat(w: ArrayLike) -> Vec:
    """Skew matrix [w]x such that hat(w) @ v == cross(w, v); for vectors (..., 3) the
    matrices (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = np.zeros_like(x)
    rows = [[zero, -z, y], [z, zero, -x], [-y, x, zero]]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def vee(W: ArrayLike) -> Vec:
    """Inverse of hat: the vector of a skew matrix (antisymmetric part used)."""
    W = np.asarray(W, dtype=float)
    return 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def exp_so3(w: ArrayLike) -> Vec:
    """Rotation matrix of the rotation vector w (Rodrigues, series near 0); for vectors
    (..., 3) the matrices (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    theta2 = np.einsum("...i,...i->...", w, w)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    W = hat(w)
    return np.eye(3) + a * W + b * (W @ W)


def rotvec_to_quat4(wx: float, wy: float, wz: float) -> tuple[float, float, float, float]:
    """Unit quaternion of the rotation vector (wx, wy, wz); scalar hot path."""
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    # sin(theta/2) / theta, by its series near 0
    s = 0.5 - theta * theta / 48.0 if theta < _SMALL_ANGLE else math.sin(0.5 * theta) / theta
    return (math.cos(0.5 * theta), s * wx, s * wy, s * wz)


def quats_to_matrices(q: ArrayLike) -> Vec:
    """Rotation matrices (N x 3 x 3) of unit quaternions (N x 4, w first)."""
    q = np.asarray(q, dtype=float)
    return np.stack(quat_to_r9(*q.T), axis=1).reshape(-1, 3, 3)


def quat_from_rotvec(w: ArrayLike) -> Vec:
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation vector w."""
    wx, wy, wz = np.asarray(w, dtype=float).reshape(3).tolist()
    return canonical_quat(np.array(rotvec_to_quat4(wx, wy, wz)))


def rotvec_from_quat(q: ArrayLike) -> Vec:
    """Rotation vector (angle in [0, pi]) of a unit quaternion, either sign."""
    return np.array(quat4_to_rotvec(*canonical_quat(q).tolist()))


@register_jitable  # the scalar forms: plain Python here, compiled where a kernel calls them
def quat4_to_rotvec(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Rotation vector (angle in [0, pi]) of a unit quaternion; scalar hot path."""
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # 2 atan2(s, w) / s, by its series 2/w (1 - s^2/(3 w^2)) for small s
    k = (
        (2.0 / w) * (1.0 - s * s / (3.0 * w * w))
        if s < _SMALL_ANGLE
        else 2.0 * math.atan2(s, w) / s
    )
    return (k * x, k * y, k * z)


def quats_to_rotvecs(q: ArrayLike) -> Vec:
    """quat4_to_rotvec for each row of an (m, 4) array of unit quaternions: (m, 3)."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[:, :1] < 0.0, -q, q)
    w, v = q[:, 0], q[:, 1:]
    s = np.sqrt(np.einsum("ij,ij->i", v, v))
    small = s < _SMALL_ANGLE
    with np.errstate(divide="ignore", invalid="ignore"):  # each branch where it is not used
        k = np.where(small, (2.0 / w) * (1.0 - s * s / (3.0 * w * w)), 2.0 * np.arctan2(s, w) / s)
    return k[:, None] * v


def log_so3(R: ArrayLike) -> Vec:
    """Rotation vector of R, accurate near 0 and near pi."""
    return rotvec_from_quat(quat_from_matrix(R))


def canonical_quat(q: ArrayLike) -> Vec:
    """q with the sign chosen so that w >= 0 (first non-zero component positive at w == 0)."""
    q = np.asarray(q, dtype=float).reshape(4)
    for c in q:
        if c != 0.0:
            return -q if c < 0.0 else q.copy()
    return q.copy()


def quat_to_r9(w: float, x: float, y: float, z: float) -> tuple[float, ...]:
    """Row-major rotation matrix (9 floats) of a unit quaternion; scalar hot path."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (
        1.0 - 2.0 * (yy + zz),
        2.0 * (xy - wz),
        2.0 * (xz + wy),
        2.0 * (xy + wz),
        1.0 - 2.0 * (xx + zz),
        2.0 * (yz - wx),
        2.0 * (xz - wy),
        2.0 * (yz + wx),
        1.0 - 2.0 * (xx + yy),
    )


def quat_to_matrix(q: ArrayLike) -> Vec:
    """Rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(c) for c in np.asarray(q, dtype=float).reshape(4))
    return np.array(quat_to_r9(w, x, y, z)).reshape(3, 3)


def quat_from_matrix(R: ArrayLike) -> Vec:
    """Unit quaternion (w >= 0) of a rotation matrix, by Shepperd's method: from the
    largest of 1 + trace and the diagonal's four signed sums; for matrices (..., 3, 3)
    the quaternions (..., 4)."""
    R = np.asarray(R, dtype=float)
    m = R.reshape(-1, 3, 3)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    s21, s02, s10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    p01, p02, p12 = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    sums = np.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22]
    )
    k = np.argmax(sums, axis=0)
    rows = np.arange(len(k))
    r2 = sums[k, rows]  # the chosen sum is at least 1
    r = np.sqrt(r2)
    candidates = np.stack(  # per k: (w, x, y, z) times 2 r, its own entry r / 2 times 2 r
        [
            np.stack([r2, s21, s02, s10]),
            np.stack([s21, r2, p01, p02]),
            np.stack([s02, p01, r2, p12]),
            np.stack([s10, p02, p12, r2]),
        ]
    )
    q = candidates[k, :, rows] / (2.0 * r)[:, None]
    q /= np.linalg.norm(q, axis=1)[:, None]
    # canonical: the first non-zero component positive (w >= 0)
    first = np.argmax(q != 0.0, axis=1)
    q *= np.where(q[rows, first] < 0.0, -1.0, 1.0)[:, None]
    return q.reshape((*R.shape[:-2], 4))


@register_jitable
def quat_mul4(
    aw: float, ax: float, ay: float, az: float, bw: float, bx: float, by: float, bz: float
) -> tuple[float, float, float, float]:
    """Hamilton product a * b on scalars; scalar hot path."""
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_multiply(a: ArrayLike, b: ArrayLike) -> Vec:
    """Hamilton product a * b (rotation b first, then a)."""
    a = np.asarray(a, dtype=float).reshape(4).tolist()
    b = np.asarray(b, dtype=float).reshape(4).tolist()
    return np.array(quat_mul4(*a, *b))


def rotate_quat_by_rotvec(
    q: tuple[float, float, float, float], wx: float, wy: float, wz: float
) -> tuple[float, float, float, float]:
    """exp(w) * q, renormalised: the rotation part of a mixed-coordinate step."""
    aw, ax, ay, az = rotvec_to_quat4(wx, wy, wz)
    bw, bx, by, bz = q
    w, x, y, z = quat_mul4(aw, ax, ay, az, bw, bx, by, bz)
    n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    return (w * n, x * n, y * n, z * n)
