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
from numpy.typing import ArrayLike, NDArray

from cdpr import so3

QUATERNION_NORM_TOLERANCE = 1e-6


class Pose:
    """Immutable platform pose: position (world, m) and rotation platform -> world.

    ``Pose(position=(x, y, z), quaternion=(w, x, y, z))``; the quaternion must be
    unit within QUATERNION_NORM_TOLERANCE and is stored normalised with w >= 0.
    """

    __slots__ = ("_R", "_p", "_q")

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
        p.setflags(write=False)
        self._p = p
        self._q = so3.canonical_quat(q / norm)
        self._q.setflags(write=False)
        self._R: NDArray[np.float64] | None = None

    @classmethod
    def _from_unit(cls, position: Sequence[float], quaternion: Sequence[float]) -> Pose:
        """Fast path for values the model computed itself: finite, unit quaternion."""
        self = cls.__new__(cls)
        p = np.array(position, dtype=float)
        p.setflags(write=False)
        q = np.array(quaternion, dtype=float)
        if q[0] < 0.0:
            q = -q
        q.setflags(write=False)
        self._p, self._q, self._R = p, q, None
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
        return self._p

    @property
    def quaternion(self) -> NDArray[np.float64]:
        """Unit quaternion (w, x, y, z), w >= 0, read-only array."""
        return self._q

    @property
    def rotation(self) -> NDArray[np.float64]:
        """Rotation matrix R (platform -> world), read-only array."""
        if self._R is None:
            R = so3.quat_to_matrix(self._q)
            R.setflags(write=False)
            self._R = R
        return self._R

    def as_dict(self) -> dict:
        """Interface form: position list and quaternion as an object with named keys."""
        w, x, y, z = self._q.tolist()
        return {"position": self._p.tolist(), "quaternion": {"w": w, "x": x, "y": y, "z": z}}

    def __repr__(self) -> str:
        p = ", ".join(f"{c:.6g}" for c in self._p)
        q = ", ".join(f"{c:.6g}" for c in self._q)
        return f"Pose(position=({p}), quaternion=({q}))"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pose):
            return NotImplemented
        return bool(np.array_equal(self._p, other._p) and np.array_equal(self._q, other._q))

    def __hash__(self) -> int:
        return hash((tuple(self._p.tolist()), tuple(self._q.tolist())))


def liediff(eta1: Pose, eta2: Pose) -> NDArray[np.float64]:
    """The paper's eta2 (-) eta1 in mixed coordinates: (p2 - p1, log(R2 R1^T))."""
    w1, x1, y1, z1 = eta1._q.tolist()
    dq = so3.quat_mul4(*eta2._q.tolist(), w1, -x1, -y1, -z1)
    (a, b, c), (d, e, f) = eta1._p.tolist(), eta2._p.tolist()
    return np.array((d - a, e - b, f - c, *so3.quat4_to_rotvec(*dq)))


def retract(eta: Pose, theta: Sequence[float] | NDArray[np.float64]) -> Pose:
    """eta (+) theta: move by a mixed tangent vector (dp, dw): (p + dp, exp(dw) R)."""
    dx, dy, dz, wx, wy, wz = np.asarray(theta, dtype=float).reshape(6).tolist()
    if not math.isfinite(dx + dy + dz + wx + wy + wz):
        raise ValueError(f"cannot retract by a non-finite tangent vector {theta!r}")
    q = so3.rotate_quat_by_rotvec(tuple(eta.quaternion.tolist()), wx, wy, wz)
    x, y, z = eta.position.tolist()
    return Pose._from_unit((x + dx, y + dy, z + dz), q)
