"""The geometric path of one motion (rest to rest): straight lines between the poses in
a 6-D space q = (position, l theta), theta the rotation vector of R R0^T and l the robot's
moment length (a radian counts as l metres of path), each corner rounded by a quintic
that leaves and joins the lines with their direction and no curvature, so that q(s) is
twice continuously differentiable in the path length s (what time-optimal
parameterisation needs: q, q', q'').

A blend of radius r starts r before the corner and ends r after it (r at most half of
either line, so that blends never overlap); on it q(s) = H(tau), tau = (s - s0) / (2 r),
the quintic Hermite with H(0), H(1) the two points, H'(0) = 2 r u_in, H'(1) = 2 r u_out,
H''(0) = H''(1) = 0: |q'| is 1 at both ends and close to it between.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cdpr.pose import Pose
from cdpr.so3 import exp_so3, quat_from_matrix, quats_to_rotvecs
from cdpr.trajectory.core import TrajectoryError
from cdpr.trajectory.rotation import angular_rates

Array = NDArray[np.float64]

_STRAIGHT = 1e-9  # |u_out - u_in| below this: the lines go on straight, no corner
# m of path: a line between two blends shorter than this is rounding, none (a blend of
# half a segment on each side leaves 1e-17 m, and grid points that coincide)
_NO_LINE = 1e-9


def _hermite(tau: Array, order: int) -> tuple[Array, Array, Array, Array]:
    """The quintic Hermite basis for H(0), H'(0), H(1), H'(1) (zero H''), its `order`-th
    derivative in tau."""
    t = tau
    if order == 0:
        return (
            1 - 10 * t**3 + 15 * t**4 - 6 * t**5,
            t - 6 * t**3 + 8 * t**4 - 3 * t**5,
            10 * t**3 - 15 * t**4 + 6 * t**5,
            -4 * t**3 + 7 * t**4 - 3 * t**5,
        )
    if order == 1:
        return (
            -30 * t**2 + 60 * t**3 - 30 * t**4,
            1 - 18 * t**2 + 32 * t**3 - 15 * t**4,
            30 * t**2 - 60 * t**3 + 30 * t**4,
            -12 * t**2 + 28 * t**3 - 15 * t**4,
        )
    return (
        -60 * t + 180 * t**2 - 120 * t**3,
        -36 * t + 96 * t**2 - 60 * t**3,
        60 * t - 180 * t**2 + 120 * t**3,
        -24 * t + 84 * t**2 - 60 * t**3,
    )


def path_coordinates(poses: Sequence[Pose], origin: Array, length: float) -> Array:
    """q = (position, l theta) of each of `poses` (N x 6), theta the rotation vector of
    R origin^T and l the moment `length` (module docstring)."""
    positions = np.array([pose.position_tuple for pose in poses])
    turns = np.array([pose.rotation for pose in poses]) @ origin.T
    return np.hstack([positions, length * quats_to_rotvecs(quat_from_matrix(turns))])


class BlendedPath:
    """q(s) through `poses` (one motion, rest to rest) with each interior corner rounded
    by its `blends` entry (m; 0: none, allowed only where the lines go on straight), q in
    the 6-D space of the module docstring with moment length `length` (m).  Callable as
    toppra's geometric paths are: path(s, order) for s a float or an array."""

    def __init__(self, poses: list[Pose], blends: list[float], length: float) -> None:
        self.length = length
        self.origin = poses[0].rotation
        nodes = path_coordinates(poses, self.origin, length)
        if np.any(np.linalg.norm(nodes[:, 3:], axis=1) > 0.9 * np.pi * length):
            raise TrajectoryError(
                "path_rotation", "a motion turns the platform by nearly 180 deg or more"
            )
        steps = np.diff(nodes, axis=0)
        norms = np.linalg.norm(steps, axis=1)
        units = steps / norms[:, None]
        radii = np.zeros(len(nodes))  # each corner's blend (none at the ends)
        if len(nodes) > 2:
            bent = np.linalg.norm(np.diff(units, axis=0), axis=1) > _STRAIGHT
            half = 0.5 * np.minimum(norms[:-1], norms[1:])
            radii[1:-1] = np.where(bent, np.minimum(np.asarray(blends[1:-1], float), half), 0.0)
            unblended = np.flatnonzero(bent & ~(radii[1:-1] > 0.0))
            if unblended.size:
                raise ValueError(
                    f"pose {unblended[0] + 1}: a corner without a blend inside a motion"
                )
        runs = norms - radii[:-1] - radii[1:]  # each line less the blends at its ends
        # parts: (s0, s1, kind, data): kind 0 a line (start, unit), 1 a blend (A, V0, B, V1)
        self._parts: list[tuple[float, float, int, tuple[Array, ...]]] = []
        self._segments: list[tuple[int, ...]] = []  # the segments (their end points) of each
        s = 0.0
        for i, (run, r) in enumerate(zip(runs.tolist(), radii[1:].tolist(), strict=True), 1):
            u_in = units[i - 1]
            if run > _NO_LINE:
                self._parts.append((s, s + run, 0, (nodes[i - 1] + radii[i - 1] * u_in, u_in)))
                self._segments.append((i,))
                s += run
            if r > 0.0:
                u_out, span = units[i], 2.0 * r
                data = (nodes[i] - r * u_in, span * u_in, nodes[i] + r * u_out, span * u_out)
                self._parts.append((s, s + span, 1, data))
                self._segments.append((i, i + 1))
                s += span
        self.s_end = s
        self._starts = np.array([p[0] for p in self._parts])
        # the parts as arrays, for evaluating at many s at once: a line's data is
        # (start, unit, 0, 0), a blend's its Hermite data
        self._lines = np.array([kind == 0 for _, _, kind, _ in self._parts])
        self._spans = np.array([s1 - s0 for s0, s1, _, _ in self._parts])
        self._data = np.zeros((len(self._parts), 4, 6))
        for k, (_, _, _, data) in enumerate(self._parts):
            self._data[k, : len(data)] = data

    def part_at(self, s: Array) -> NDArray[np.intp]:
        """The index of the part (parts(), part_segments) each path length s lies on."""
        return np.clip(np.searchsorted(self._starts, s, side="right") - 1, 0, None)

    @property
    def part_segments(self) -> list[tuple[int, ...]]:
        """The segments each part is on (each named by the pose it ends at): one for a
        line, the two it joins for a blend."""
        return self._segments

    def parts(self) -> list[tuple[float, float, bool]]:
        """The path's pieces in order: (s0, s1, True on a blend, False on a line)."""
        return [(s0, s1, kind == 1) for s0, s1, kind, _ in self._parts]

    @property
    def dof(self) -> int:
        return 6

    @property
    def path_interval(self) -> Array:
        return np.array([0.0, self.s_end])

    @property
    def waypoints(self) -> None:
        return None

    def __call__(self, s: float | Array, order: int = 0) -> Array:
        scalar = np.ndim(s) == 0
        ss = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self.s_end)
        which = self.part_at(ss)
        local = ss - self._starts[which]
        data = self._data[which]
        line = self._lines[which]
        out = np.zeros((len(ss), 6))
        if order == 0:
            out[line] = data[line, 0] + local[line, None] * data[line, 1]
        elif order == 1:
            out[line] = data[line, 1]
        blend = ~line
        span = self._spans[which[blend], None]
        basis = _hermite(local[blend] / span[:, 0], order)
        points = data[blend]
        out[blend] = sum(b[:, None] * points[:, j] for j, b in enumerate(basis)) / span**order
        return out[0] if scalar else out

    def eval(self, s: float | Array) -> Array:
        return self(s, 0)

    def evald(self, s: float | Array) -> Array:
        return self(s, 1)

    def evaldd(self, s: float | Array) -> Array:
        return self(s, 2)

    def poses(self, s: Array) -> tuple[Array, Array, Array, Array, Array, Array]:
        """At each path length s: positions (N, 3), rotations (N, 3, 3), and per unit s
        the linear and angular rates p', w_s and their derivatives p'', w_ss (world
        frame; the platform's twist is (p', w_s) s', its accel (p', w_s) s'' + (p'',
        w_ss) s'^2)."""
        q, dq, ddq = self(s, 0), self(s, 1), self(s, 2)
        theta, dtheta, ddtheta = (x[:, 3:] / self.length for x in (q, dq, ddq))
        rotations = exp_so3(theta) @ self.origin
        omega, omega_dot = angular_rates(theta.T, dtheta.T, ddtheta.T)
        return (
            q[:, :3],
            rotations,
            dq[:, :3],
            np.array(omega).T,
            ddq[:, :3],
            np.array(omega_dot).T,
        )
