"""The interface form of a path (JSON over zenoh, a file for `cdprd send --path` and
`cdprd plan`), version 1:

    {"version": 1,                                        # optional; 1 if given
     "poses": [
       {"position": [0.0, 0.0, 1.25],                     # m, or {"x": .., "y": .., "z": ..}
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0}},
       {"position": [0.2, 0.0, 1.25],                     # quaternion: the previous one's
        "speed": 0.3,                                     # m/s on the segment ending here
        "blend": 0.02,                                    # m: round this corner
        "dwell": 0.5},                                    # s at rest here
       ...]}

The first pose needs its quaternion; a later one without keeps the previous one's.  The
same rules as a trajectory's (cdpr.trajectory.parse): unknown keys, wrong types,
non-finite numbers and quaternions off unit are refused with TrajectoryError naming the
pose and the field; at most trajectory.max_waypoints poses.
"""

from __future__ import annotations

from typing import Any

from cdpr.path.model import Path, PathPoint
from cdpr.pose import Pose
from cdpr.trajectory.core import TrajectoryError
from cdpr.trajectory.limits import TrajectoryLimits
from cdpr.trajectory.parse import _keys, _number, _quaternion, _vec3, items

_OPTIONS = ("quaternion", "speed", "blend", "dwell")


def parse_path(data: Any, limits: TrajectoryLimits | None = None) -> Path:
    """Build a Path from its interface form; TrajectoryError on any bad input."""
    limits = TrajectoryLimits() if limits is None else limits
    raw = items(data, "poses", "path", limits)
    points: list[PathPoint] = []
    quaternion: list[float] | None = None
    for i, item in enumerate(raw):
        where = f"poses[{i}]"
        required = ("position",) if i else ("position", "quaternion")
        _keys(item, required, _OPTIONS, where, i)
        position = _vec3(item["position"], f"{where}.position", i)
        if item.get("quaternion") is not None or quaternion is None:
            tolerance = limits.unit_tolerance
            quaternion = _quaternion(item["quaternion"], f"{where}.quaternion", i, tolerance)
        options = {}
        for name in ("speed", "blend", "dwell"):
            if item.get(name) is not None:
                options[name] = _number(item[name], f"{where}.{name}", i)
        try:
            points.append(PathPoint(Pose(position, quaternion), **options))
        except TrajectoryError as exc:
            detail = str(exc).removeprefix(f"{exc.limit}: ")
            raise TrajectoryError(exc.limit, f"{where}.{detail}", waypoint=i, field=where) from None
    return Path(tuple(points))
