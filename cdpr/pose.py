"""Platform pose eta = (p, R) and the mixed-coordinate tangent operations.

Tangent vectors are MIXED (DESIGN §3): theta = (dp, dw) with dp a world-frame
displacement of the reference point and dw a world-frame rotation vector, so
``retract(eta, theta) = (p + dp, exp(dw) R)`` and
``liediff(eta1, eta2) = (p2 - p1, log(R2 R1^T))``, i.e. eta2 = retract(eta1, liediff(eta1, eta2)).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba.extending import register_jitable
from numpy.typing import ArrayLike, NDArray

from cdpr import so3

QUATERNION_NORM_TOLERANCE = 1e-6


class Pose:
    """Immutable platform pose: position (world, m) and rotation platform -> world.

    ``Pose(position=(x, y, z), quaternion=(w, x, y, z))``; the quaternion must be
    unit within QUATERNION_NORM_TOLERANCE and is stored normalised with w >= 0.

    The values are kept as tuples of floats, which the scalar hot paths read directly
    (position_tuple, quaternion_tuple); the read-only arrays are built on first access.
    """

    __slots__ = ("_R", "_p", "_pt", "_q", "_qt")

    def __init__(
        self,
        position: ArrayLike = (0.0, 0.0, 0.0),
        quaternion: ArrayLike = (1.0, 0.0, 0.0, 0.0),
    ) -> None:
        p = np.array(position, dtype=float)
        q = np.array(quaternion, dtype=float)
        if p.shape != (3,):
            raise ValueError(f"pose position must have 3 components, got shape {p.shape}")
        if q.shape != (4,):
            raise ValueError(f"pose quaternion must have 4 components (w, x, y, z), got {q.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise ValueError(f"pose has non-finite values: position {p}, quaternion {q}")
        norm = math.sqrt(float(q @ q))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise ValueError(
                f"pose quaternion {q.tolist()} has norm {norm:.9g}; a unit quaternion is required"
            )
        self._pt = tuple(p.tolist())
        self._qt = tuple(so3.canonical_quat(q / norm).tolist())
        self._p = self._q = self._R = None

    @classmethod
    def _from_unit(cls, position: Sequence[float], quaternion: Sequence[float]) -> Pose:
        """Fast path for values the model computed itself: Python floats, finite, unit
        quaternion."""
        self = cls.__new__(cls)
        if quaternion[0] < 0.0:
            quaternion = [-c for c in quaternion]
        self._pt = tuple(position)
        self._qt = tuple(quaternion)
        self._p = self._q = self._R = None
        return self

    @classmethod
    def from_matrix(cls, position: ArrayLike, rotation: ArrayLike) -> Pose:
        """Pose from a position and a 3x3 rotation matrix."""
        return cls(position, so3.quat_from_matrix(rotation))

    @classmethod
    def from_rotvec(cls, position: ArrayLike, rotvec: ArrayLike = (0.0, 0.0, 0.0)) -> Pose:
        """Pose from a position and a world-frame rotation vector (rad)."""
        return cls(position, so3.quat_from_rotvec(rotvec))

    @property
    def position(self) -> NDArray[np.float64]:
        """Reference point p in the world frame (m), read-only array."""
        if self._p is None:
            self._p = _read_only(self._pt)
        return self._p

    @property
    def quaternion(self) -> NDArray[np.float64]:
        """Unit quaternion (w, x, y, z), w >= 0, read-only array."""
        if self._q is None:
            self._q = _read_only(self._qt)
        return self._q

    @property
    def position_tuple(self) -> tuple[float, float, float]:
        """The position as a tuple of floats (for scalar code)."""
        return self._pt

    @property
    def quaternion_tuple(self) -> tuple[float, float, float, float]:
        """The quaternion (w, x, y, z), w >= 0, as a tuple of floats (for scalar code)."""
        return self._qt

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Rotation matrix R (platform -> world), read-only array."""
        if self._R is None:
            self._R = _read_only(so3.quat_to_r9(*self._qt)).reshape(3, 3)
        return self._R

    def as_dict(self) -> dict:
        """Interface form: position list and quaternion as an object with named keys."""
        w, x, y, z = self._qt
        return {"position": list(self._pt), "quaternion": {"w": w, "x": x, "y": y, "z": z}}

    def __repr__(self) -> str:
        p = ", ".join(f"{c:.6g}" for c in self._pt)
        q = ", ".join(f"{c:.6g}" for c in self._qt)
        return f"Pose(position=({p}), quaternion=({q}))"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return self._pt == other._pt and self._qt == other._qt

    def __hash__(self) -> int:
        return hash((self._pt, self._qt))


def _read_only(values: Sequence[float]) -> NDArray[np.float64]:
    a = np.array(values, dtype=float)
    a.setflags(write=False)
    return a


def liediff(eta1: Pose, eta2: Pose) -> NDArray[np.float64]:
    """The paper's eta2 (-) eta1 in mixed coordinates: (p2 - p1, log(R2 R1^T))."""
    return np.array(liediff6(eta1, eta2))


def liediff6(eta1: Pose, eta2: Pose) -> tuple[float, float, float, float, float, float]:
    """liediff as a tuple of 6 floats; scalar hot path."""
    return pose_difference(eta1._pt, eta1._qt, eta2._pt, eta2._qt)


@register_jitable  # plain Python here, compiled where a kernel calls it
def pose_difference(
    p1: Sequence[float], q1: Sequence[float], p2: Sequence[float], q2: Sequence[float]
) -> tuple[float, float, float, float, float, float]:
    """liediff on the poses' numbers (tuples or arrays): (p2 - p1, log(R2 R1^T))."""
    dq = so3.quat_mul4(q2[0], q2[1], q2[2], q2[3], q1[0], -q1[1], -q1[2], -q1[3])
    rx, ry, rz = so3.quat4_to_rotvec(dq[0], dq[1], dq[2], dq[3])
    return (p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2], rx, ry, rz)


def retract(eta: Pose, theta: Sequence[float] | NDArray[np.float64]) -> Pose:
    """eta (+) theta: move by a mixed tangent vector (dp, dw): (p + dp, exp(dw) R)."""
    dx, dy, dz, wx, wy, wz = np.asarray(theta, dtype=float).reshape(6).tolist()
    if not math.isfinite(dx + dy + dz + wx + wy + wz):
        raise ValueError(f"cannot retract by a non-finite tangent vector {theta!r}")
    q = so3.rotate_quat_by_rotvec(eta._qt, wx, wy, wz)
    x, y, z = eta._pt
    return Pose._from_unit((x + dx, y + dy, z + dz), q)
