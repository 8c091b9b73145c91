"""A path: the poses a motion passes through, in order, without times.

Each point after the first may cap the platform's linear speed on the segment that ends
at it (`speed`, m/s), round its corner (`blend`: how far before and after the corner the
path leaves the straight lines, m of path length, rotations counted at the robot's
moment length), and keep the platform at rest there (`dwell`, s).  A corner without a
blend is flown as two motions, stopping at it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cdpr.pose import Pose
from cdpr.trajectory.core import TrajectoryError


@dataclass(frozen=True)
class PathPoint:
    """One pose of a path and what it asks of the motion there (module docstring)."""

    pose: Pose
    speed: float | None = None
    blend: float = 0.0
    dwell: float = 0.0

    def __post_init__(self) -> None:
        for name, value, least in (
            ("speed", self.speed, 0.0),
            ("blend", self.blend, 0.0),
            ("dwell", self.dwell, 0.0),
        ):
            if value is None:
                continue
            if not math.isfinite(value) or value < least or (name == "speed" and value == 0.0):
                wanted = "positive" if name == "speed" else "at least 0"
                raise TrajectoryError("schema", f"{name}: {value!r} must be a {wanted} number")


@dataclass(frozen=True)
class Path:
    """Two points or more (PathPoint), the first where the motion starts."""

    points: tuple[PathPoint, ...]

    def __post_init__(self) -> None:
        if len(self.points) < 2:
            raise TrajectoryError(
                "schema", f"a path needs two poses or more, got {len(self.points)}"
            )

    def as_dict(self) -> dict:
        """The interface form (cdpr.path.parse_path reads it back): every pose with its
        quaternion, and what it asks where that is not the default."""
        poses = []
        for point in self.points:
            pose = point.pose.as_dict()
            if point.speed is not None:
                pose["speed"] = point.speed
            if point.blend:
                pose["blend"] = point.blend
            if point.dwell:
                pose["dwell"] = point.dwell
            poses.append(pose)
        return {"poses": poses}
