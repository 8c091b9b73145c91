"""Cable interference: two cables closer than their diameters, or a cable running through
the platform's body.

Each cable is the straight segment from where it leaves its anchor (the anchor, or a
pulley's leave point) to its attachment.  Two cables interfere where the segments come
closer than the mean of their diameters (closest points of two segments: Ericson,
Real-Time Collision Detection §5.1.9); cables that share an anchor or an attachment
point meet there by design and are not compared.

The body is the convex hull of the platform's corners and attachments (cdpr.body), as
half-spaces n_f . x <= h_f in the platform frame.  An attachment lies on the hull's
surface, and a straight line that leaves a convex body cannot enter it again, so cable k
runs clear of the body exactly when its direction towards the anchor, d, points out of
at least one face the attachment lies on (n_f . d > 0); otherwise it runs into the body
or along its surface.  An attachment inside the hull (on no face) always does.

Compiled with numba, like cdpr.wrench_margin: the daemon checks every sample of every
trajectory, the workspace map millions of poses.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import ConvexHull

from cdpr.compiled_cache import key_numba_cache

key_numba_cache()  # before the first @njit(cache=True): its cache keyed by the sources

Array = NDArray[np.float64]

_ON_FACE = 1e-9  # m: an attachment this close to a face's plane lies on it


class Touch(NamedTuple):
    """What interferes: cables `first` and `second` (`second` -1: `first` and the body) at
    `distance` (m; cables: closest approach, body: 0)."""

    first: int
    second: int
    distance: float


@njit(cache=True)
def segment_distance(p1: Array, q1: Array, p2: Array, q2: Array) -> float:
    """The smallest distance between segments p1-q1 and p2-q2 (m)."""
    d1x, d1y, d1z = q1[0] - p1[0], q1[1] - p1[1], q1[2] - p1[2]
    d2x, d2y, d2z = q2[0] - p2[0], q2[1] - p2[1], q2[2] - p2[2]
    rx, ry, rz = p1[0] - p2[0], p1[1] - p2[1], p1[2] - p2[2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    if a <= 1e-300 and e <= 1e-300:
        s = t = 0.0
    elif a <= 1e-300:
        s = 0.0
        t = min(max(f / e, 0.0), 1.0)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= 1e-300:
            t = 0.0
            s = min(max(-c / a, 0.0), 1.0)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = min(max(-c / a, 0.0), 1.0)
            elif t > 1.0:
                t = 1.0
                s = min(max((b - c) / a, 0.0), 1.0)
    x = rx + d1x * s - d2x * t
    y = ry + d1y * s - d2y * t
    z = rz + d1z * s - d2z * t
    return math.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def touch_kernel(
    starts: Array,
    ends: Array,
    rotation: Array,
    pairs: NDArray[np.int64],
    gaps: Array,
    faces: Array,
    on_face: NDArray[np.bool_],
) -> tuple[int, int, float]:
    """The first interference of one pose (cable, cable or -1, distance), else (-1, -1, 0).
    For compiled callers: Interference wraps it."""
    for q in range(pairs.shape[0]):
        i, j = pairs[q, 0], pairs[q, 1]
        dist = segment_distance(starts[i], ends[i], starts[j], ends[j])
        if dist < gaps[q]:
            return i, j, dist
    for k in range(starts.shape[0]):
        # the direction towards the anchor, in the platform frame: R^T (start - end)
        wx = starts[k, 0] - ends[k, 0]
        wy = starts[k, 1] - ends[k, 1]
        wz = starts[k, 2] - ends[k, 2]
        dx = rotation[0, 0] * wx + rotation[1, 0] * wy + rotation[2, 0] * wz
        dy = rotation[0, 1] * wx + rotation[1, 1] * wy + rotation[2, 1] * wz
        dz = rotation[0, 2] * wx + rotation[1, 2] * wy + rotation[2, 2] * wz
        leaves = faces.shape[0] == 0  # a body without volume or area: nothing to run through
        for f in range(faces.shape[0]):
            if on_face[k, f] and faces[f, 0] * dx + faces[f, 1] * dy + faces[f, 2] * dz > 0.0:
                leaves = True
                break
        if not leaves:
            return k, -1, 0.0
    return -1, -1, 0.0


@njit(cache=True)
def _touches_between(
    starts: Array,
    ends: Array,
    rotations: Array,
    pairs: NDArray[np.int64],
    gaps: Array,
    faces: Array,
    on_face: NDArray[np.bool_],
    out: NDArray[np.bool_],
    begin: int,
    end: int,
) -> None:
    """out[p] = does anything interfere at pose p, for p in [begin, end)."""
    for p in range(begin, end):
        out[p] = touch_kernel(starts[p], ends[p], rotations[p], pairs, gaps, faces, on_face)[0] >= 0


@njit(cache=True, parallel=True)
def _touches(
    starts: Array,
    ends: Array,
    rotations: Array,
    pairs: NDArray[np.int64],
    gaps: Array,
    faces: Array,
    on_face: NDArray[np.bool_],
    out: NDArray[np.bool_],
) -> None:
    """_touches_between over every pose, in chunks on every core."""
    count = starts.shape[0]
    chunks = min(count, 64)
    for c in prange(chunks):
        _touches_between(
            starts, ends, rotations, pairs, gaps, faces, on_face, out,
            c * count // chunks, (c + 1) * count // chunks,
        )  # fmt: skip


def hull_faces(points: Array) -> tuple[Array, Array]:
    """The convex hull of `points` as half-spaces n . x <= h (unit normals n, offsets h).
    A flat body (a plate) is its polygon's edges in its plane and the plane from both
    sides; a line or a point has none."""
    centre = points.mean(axis=0)
    _, sizes, axes = np.linalg.svd(points - centre)
    flat = sizes[2] <= _ON_FACE * max(sizes[0], 1.0) if len(sizes) == 3 else True
    if len(points) >= 4 and not flat:
        hull = ConvexHull(points)
        return hull.equations[:, :3], -hull.equations[:, 3]
    if len(sizes) < 2 or sizes[1] <= _ON_FACE * max(sizes[0], 1.0):
        return np.zeros((0, 3)), np.zeros(0)
    plane = axes[:2]  # in-plane directions; axes[2] the plate's normal
    polygon = ConvexHull((points - centre) @ plane.T)
    normals = polygon.equations[:, :2] @ plane
    offsets = -polygon.equations[:, 2] + normals @ centre
    normal = axes[2]
    return (
        np.vstack([normals, normal, -normal]),
        np.concatenate([offsets, [normal @ centre, -normal @ centre]]),
    )


class Interference:
    """The interference checks of one robot: cable `diameters` (m, per cable), the body's
    hull points, the attachments (platform frame) and the anchors (world frame, m)."""

    def __init__(
        self,
        diameters: ArrayLike,
        hull_points: ArrayLike,
        attachments: ArrayLike,
        anchors: ArrayLike,
    ) -> None:
        self.diameters = np.asarray(diameters, dtype=float)
        b = np.asarray(attachments, dtype=float)
        a = np.asarray(anchors, dtype=float)
        n = len(b)
        pairs, gaps = [], []
        for i in range(n):
            for j in range(i + 1, n):
                if np.allclose(b[i], b[j], atol=_ON_FACE) or np.allclose(a[i], a[j], atol=_ON_FACE):
                    continue  # one attachment or anchor point: they meet there by design
                pairs.append((i, j))
                gaps.append(0.5 * (self.diameters[i] + self.diameters[j]))
        self.pairs = np.array(pairs, np.int64).reshape(-1, 2)
        self.gaps = np.array(gaps, dtype=float)
        faces, offsets = hull_faces(np.asarray(hull_points, dtype=float))
        self.faces = np.ascontiguousarray(faces)
        self.on_face = np.abs(b.dot(faces.T) - offsets) <= _ON_FACE
        inside = ~self.on_face.any(axis=1) if len(faces) else np.zeros(n, np.bool_)
        self.inside = tuple(int(k) for k in np.flatnonzero(inside))

    def first(self, starts: ArrayLike, ends: ArrayLike, rotation: ArrayLike) -> Touch | None:
        """The first interference of one pose: the cables' `starts` and `ends` (n x 3,
        world) at platform rotation R, else None."""
        i, j, dist = touch_kernel(
            np.ascontiguousarray(starts, dtype=float),
            np.ascontiguousarray(ends, dtype=float),
            np.ascontiguousarray(rotation, dtype=float),
            self.pairs,
            self.gaps,
            self.faces,
            self.on_face,
        )
        return None if i < 0 else Touch(int(i), int(j), float(dist))

    def any(
        self, starts: ArrayLike, ends: ArrayLike, rotations: ArrayLike, parallel: bool = True
    ) -> NDArray[np.bool_]:
        """Per pose (N x n x 3 starts and ends, N x 3 x 3 rotations): does anything
        interfere?  On every core, or on this thread only (`parallel` False)."""
        out = np.empty(len(starts), np.bool_)
        arrays = (
            np.ascontiguousarray(starts, dtype=float),
            np.ascontiguousarray(ends, dtype=float),
            np.ascontiguousarray(rotations, dtype=float),
            self.pairs,
            self.gaps,
            self.faces,
            self.on_face,
            out,
        )
        if parallel:
            _touches(*arrays)
        else:
            _touches_between(*arrays, 0, len(out))
        return out

    def describe(self, touch: Touch) -> str:
        """One line naming what interferes."""
        if touch.second < 0:
            return f"cable {touch.first} runs through the platform's body"
        d = self.diameters
        gap = 0.5 * (d[touch.first] + d[touch.second])
        return (
            f"cables {touch.first} and {touch.second} pass {touch.distance * 1000:.1f} mm "
            f"apart, closer than their diameters allow ({gap * 1000:.1f} mm)"
        )
