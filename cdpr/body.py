"""The platform as a body, and the environment it and its cables must not cross (DESIGN §18).

A pose limit on the reference point alone lets the platform's corners through the floor:
a 0.6 m tall platform whose reference point is 0.10 m above the floor has its lower
corners 0.2 m below it.  The body is the convex hull of its corners (`PlatformBody`:
the robot file's platform.body, a box or a list of hull vertices, and every cable's
attachment point; without a body, the attachments' hull).  The environment
(`Environment`) is a list of planes (the free side is the one the normal points to: a
floor, a wall) and of boxes (axis-aligned obstacles: a table, a machine), plus the
cables' anchors, from which each cable runs straight to its attachment (a pulley's exit
point lies within its radius of the anchor: a few centimetres on the robots here).

The checks, one implementation for the runtime monitor (the measured pose, no margin)
and for validation (each sampled reference, with margins: cdpr.pose_limits):
- every corner inside the workspace box (`outside_box`);
- every corner on the free side of every plane (`crossed`): the hull is convex, so its
  corners on the free side put all of it there; a cable runs from an anchor on the free
  side (checked with the config) to a corner, so it is there too;
- the body's hull disjoint from every box, by the separating axis test (the boxes' axes,
  the hull's face normals and the cross products of its edge directions with the box
  axes: exact for two convex bodies), and every cable's segment disjoint from every box
  (slab test).

A margin (m) moves every bound inwards and grows every obstacle; `turn` (m per m of a
corner's distance from the reference point, i.e. rad) adds the motion an orientation
error gives a corner: a rotation by angle a moves a point at radius r by at most r a.
The runtime check decides the common case, a platform clear of every bound by more than
its reach, in scalar code (`Environment.near`, and PoseLimits' box test); only near a
bound do the corners get transformed and tested (cost figures: docs/explanation/safety.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cdpr.pose import Pose
from cdpr.so3 import quat_to_r9

Array = NDArray[np.float64]
_SAME_DIRECTION = 1.0 - 1e-9  # |cos| of two unit directions taken as one axis


class Plane(NamedTuple):
    """The free side of a plane: every point x with normal . x >= offset (normal unit)."""

    name: str
    normal: tuple[float, float, float]
    offset: float


class Box(NamedTuple):
    """An axis-aligned obstacle, lower < upper per axis (world frame, m)."""

    name: str
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]


@dataclass(frozen=True)
class Environment:
    """What the platform and the cables must not cross: `planes`, `boxes`, and the
    cables' `anchors` (world frame, one row per cable), where each cable starts."""

    planes: tuple[Plane, ...] = ()
    boxes: tuple[Box, ...] = ()
    anchors: tuple[tuple[float, float, float], ...] = ()

    @property
    def empty(self) -> bool:
        return not self.planes and not self.boxes

    def near(self, position: Sequence[float], reach: float) -> bool:
        """False if a body within `reach` (m) of `position` and the cables from the
        anchors to it are certainly clear of every plane and box (scalar, a few
        microseconds: the cycle's common case); True if the exact test must decide."""
        x, y, z = position
        for plane in self.planes:
            nx, ny, nz = plane.normal
            if nx * x + ny * y + nz * z - plane.offset < reach:
                return True
        lx, ly, lz = x - reach, y - reach, z - reach
        hx, hy, hz = x + reach, y + reach, z + reach
        for box in self.boxes:
            (bx, by, bz), (ux, uy, uz) = box.lower, box.upper
            # the box of each cable's segment (anchor to anywhere on the body) against it
            for ax, ay, az in self.anchors:
                if (
                    min(ax, lx) <= ux
                    and max(ax, hx) >= bx
                    and min(ay, ly) <= uy
                    and max(ay, hy) >= by
                    and min(az, lz) <= uz
                    and max(az, hz) >= bz
                ):
                    return True
        return False


class PlatformBody:
    """The platform's corners (platform frame, m): the hull vertices of its body and its
    cables' attachment points, without repeats; `attachment_of[k]` is the corner cable k
    is attached to."""

    def __init__(self, corners: Sequence[Sequence[float]], attachments: Sequence[Sequence[float]]):
        points: list[tuple[float, float, float]] = []
        for c in [*corners, *attachments]:
            point = (float(c[0]), float(c[1]), float(c[2]))
            if point not in points:
                points.append(point)
        self.corners = tuple(points)
        self.attachment_of = tuple(points.index(tuple(map(float, a))) for a in attachments)
        self.points: Array = np.array(points)
        self.radii: Array = np.linalg.norm(self.points, axis=1)
        self.radius_list: list[float] = self.radii.tolist()
        self.reach = float(self.radii.max())  # m: the farthest corner from p
        self._normals, self._edges = _hull_axes(self.points)

    def placed(self, pose: Pose) -> list[tuple[float, float, float]]:
        """The corners in the world frame at `pose`, as tuples (scalar: for a handful of
        corners cheaper than numpy's per-call overhead)."""
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = quat_to_r9(*pose.quaternion_tuple)
        px, py, pz = pose.position_tuple
        return [
            (
                px + r0 * x + r1 * y + r2 * z,
                py + r3 * x + r4 * y + r5 * z,
                pz + r6 * x + r7 * y + r8 * z,
            )
            for x, y, z in self.corners
        ]

    def world(self, rotation: Array, position: Array) -> Array:
        """The corners in the world frame at a pose (R, p): one row per corner."""
        return self.points.dot(rotation.T) + position

    def name(self, corner: int) -> str:
        x, y, z = self.corners[corner]
        return f"platform corner {corner} ({x:g}, {y:g}, {z:g} m in the platform frame)"

    def meets(self, world: Array, rotation: Array, box: Box, grow: float) -> bool:
        """True if the hull of the corners `world` (at rotation R) meets `box` grown by
        `grow` (m) on every side (one pose of `meets_many`)."""
        return bool(self.meets_many(world[None], rotation, box, grow)[0])

    def meets_many(self, world: Array, rotation: Array, box: Box, grow: float) -> NDArray[np.bool_]:
        """Per pose (world: N x corners x 3, one rotation R): does the corners' hull meet
        `box` grown by `grow` (m) on every side?  No separating axis among the box's axes,
        the hull's face normals and the cross products of its edge directions with the
        box's axes."""
        lower = np.array(box.lower) - grow
        upper = np.array(box.upper) + grow
        centre, half = (lower + upper) / 2.0, (upper - lower) / 2.0
        edges = self._edges.dot(rotation.T)
        m, f = len(edges), len(self._normals)
        axes = np.zeros((3 + f + 3 * m, 3))
        axes[:3] = np.eye(3)
        axes[3 : 3 + f] = self._normals.dot(rotation.T)
        x, y, z = edges[:, 0], edges[:, 1], edges[:, 2]
        crosses = axes[3 + f :]  # e_x, e_y, e_z each crossed with every edge direction
        crosses[:m, 1], crosses[:m, 2] = -z, y
        crosses[m : 2 * m, 0], crosses[m : 2 * m, 2] = z, -x
        crosses[2 * m :, 0], crosses[2 * m :, 1] = -y, x
        projected = world.dot(axes.T)  # N x corners x axes
        reach = np.abs(axes).dot(half)
        middle = axes.dot(centre)
        apart = (projected.max(axis=1) < middle - reach) | (projected.min(axis=1) > middle + reach)
        return ~apart.any(axis=1)


def _hull_axes(points: Array) -> tuple[Array, Array]:
    """The face normals and the edge directions of the points' convex hull, unit rows, one
    per direction.  Edges: the directions between every two points (a superset, which the
    separating axis test allows: an extra axis only finds a gap that is there).  Faces:
    the cross products of two of those whose plane touches the points on one side in at
    least three of them (the plane itself for flat points, none for collinear ones)."""
    pairs = np.array([b - a for i, a in enumerate(points) for b in points[i + 1 :]])
    edges = _directions(pairs.reshape(-1, 3))
    scale = max(float(np.abs(points).max()), 1e-9)
    faces = []
    for i, e in enumerate(edges):
        for f in edges[i + 1 :]:
            n = np.cross(e, f)
            if np.linalg.norm(n) <= 1e-9:
                continue
            heights = points.dot(n / np.linalg.norm(n))
            touching = np.abs(heights - heights.max()) <= 1e-9 * scale
            touching_low = np.abs(heights - heights.min()) <= 1e-9 * scale
            if touching.sum() >= 3 or touching_low.sum() >= 3:
                faces.append(n)
    return _directions(np.array(faces).reshape(-1, 3)), edges


def _directions(vectors: Array) -> Array:
    """Unit rows of `vectors`, one per direction (v and -v are one), zero rows dropped."""
    kept: list[Array] = []
    for v in vectors:
        n = float(np.linalg.norm(v))
        if n <= 1e-12:
            continue
        u = v / n
        if all(abs(float(u.dot(k))) < _SAME_DIRECTION for k in kept):
            kept.append(u)
    return np.array(kept).reshape(-1, 3)


def segment_meets(
    start: Sequence[float], end: Sequence[float], lower: Sequence[float], upper: Sequence[float]
) -> bool:
    """Does the segment from `start` to `end` meet the box from `lower` to `upper`?  The
    slab test: the parameter ranges inside the three slabs overlap within [0, 1]."""
    enter, leave = 0.0, 1.0
    for a, b, lo, hi in zip(start, end, lower, upper, strict=True):
        d = b - a
        if d == 0.0:
            if not lo <= a <= hi:
                return False
            continue
        t0, t1 = (lo - a) / d, (hi - a) / d
        if t0 > t1:
            t0, t1 = t1, t0
        enter, leave = max(enter, t0), min(leave, t1)
        if enter > leave:
            return False
    return True


def segments_meet(starts: Array, ends: Array, lower: Array, upper: Array) -> NDArray[np.bool_]:
    """`segment_meets` for many segments at once (starts, ends: N x 3), one box."""
    d = ends - starts
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (np.asarray(lower) - starts) / d
        t1 = (np.asarray(upper) - starts) / d
    flat = d == 0.0
    inside = (starts >= lower) & (starts <= upper)
    near = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    far = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    enter = np.maximum(near.max(axis=1), 0.0)
    leave = np.minimum(far.min(axis=1), 1.0)
    return enter <= leave


class Crossing(NamedTuple):
    """What crossed what: `part` ("platform corner 3 (...)", "cable 2", "the platform
    body"), `obstacle` ("plane 'floor'", "box 'table'"), `value` the corner's signed
    distance from a plane (m; negative: behind it), else 0, and one readable line."""

    part: str
    obstacle: str
    value: float
    detail: str


def _near_plane(part: str, plane: Plane, distance: float, clearance: float) -> Crossing:
    obstacle = f"plane '{plane.name}'"
    if distance < 0.0:
        detail = f"{part} lies {-distance:.4f} m behind {obstacle}"
    else:
        detail = (
            f"{part} lies {distance:.4f} m in front of {obstacle}, within the margin of "
            f"{clearance:.4g} m"
        )
    return Crossing(part, obstacle, distance, detail)


def _in_box(part: str, box: Box) -> Crossing:
    obstacle = f"box '{box.name}'"
    return Crossing(part, obstacle, 0.0, f"{part} crosses {obstacle}")


def crossed(
    body: PlatformBody,
    environment: Environment,
    pose: Pose,
    corners: list[tuple[float, float, float]],
    grow: float,
    turn: float,
) -> Crossing | None:
    """The first part of the platform at `pose`, its corners at `corners` (world frame),
    that crosses the environment grown by `grow` + `turn` x the corner's radius (planes,
    corners in boxes) or the body's largest radius (the body and the cables vs boxes),
    else None: the corners against the planes, then against each box the corners, the
    body and the cables.  Scalar but for the separating axis test, which runs only where
    the body's bounding box meets the obstacle's."""
    clearance = [grow + turn * r for r in body.radius_list]
    for plane in environment.planes:
        nx, ny, nz = plane.normal
        for k, ((x, y, z), clear) in enumerate(zip(corners, clearance, strict=True)):
            distance = nx * x + ny * y + nz * z - plane.offset
            if not distance >= clear:
                return _near_plane(body.name(k), plane, distance, clear)
    if not environment.boxes:
        return None
    widest = grow + turn * body.reach
    xs, ys, zs = zip(*corners, strict=True)
    body_low = (min(xs) - widest, min(ys) - widest, min(zs) - widest)
    body_high = (max(xs) + widest, max(ys) + widest, max(zs) + widest)
    for box in environment.boxes:
        if all(lo <= u for lo, u in zip(body_low, box.upper, strict=True)) and all(
            hi >= b for hi, b in zip(body_high, box.lower, strict=True)
        ):
            for k, (point, clear) in enumerate(zip(corners, clearance, strict=True)):
                if all(
                    b - clear <= v <= u + clear
                    for v, b, u in zip(point, box.lower, box.upper, strict=True)
                ):
                    return _in_box(body.name(k), box)
            if body.meets(np.array(corners), pose.rotation, box, widest):
                return _in_box("the platform body", box)
        low = [v - widest for v in box.lower]
        high = [v + widest for v in box.upper]
        for k, (anchor, a) in enumerate(zip(environment.anchors, body.attachment_of, strict=True)):
            if segment_meets(anchor, corners[a], low, high):
                return _in_box(f"cable {k}", box)
    return None
