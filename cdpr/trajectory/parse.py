"""The interface form of a trajectory (JSON over zenoh, YAML from the CLI), version 1.

    {"version": 1,                                   # optional; 1 if given
     "waypoints": [
       {"t": 0.0,                                    # s
        "position": [0.0, 0.0, 1.25],                # m, or {"x": .., "y": .., "z": ..}
        "quaternion": {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0},   # platform -> world
        "twist": {"linear": [0, 0, 0], "angular": [0, 0, 0]},    # optional: m/s, rad/s
        "accel": {"linear": [0, 0, 0], "angular": [0, 0, 0]}},   # optional: m/s², rad/s²
       ...]}

Times are seconds on the trajectory's own clock (the daemon shifts them to "now").
twist / accel (world-frame v, ω and p̈, ω̇; absent or null = chosen by the trajectory)
are optional at every waypoint; at the last one they must be zero.  Vectors may also be
{"x": .., "y": .., "z": ..} objects.

Quaternions are objects with named keys, never bare arrays; within the unit tolerance
they are normalised, beyond it rejected.  Unknown keys, wrong types and non-finite
numbers are rejected.  Any bad input raises TrajectoryError naming the waypoint and the
field, never another exception.
"""

from __future__ import annotations

import math
from typing import Any

from cdpr.pose import Pose
from cdpr.trajectory.core import SCHEMA_VERSION, Trajectory, TrajectoryError, Waypoint
from cdpr.trajectory.limits import TrajectoryLimits

_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")


def parse_trajectory(data: Any, limits: TrajectoryLimits | None = None) -> Trajectory:
    """Build a Trajectory from its interface form; TrajectoryError on any bad input."""
    limits = TrajectoryLimits() if limits is None else limits
    _keys(data, ("waypoints",), ("version",), "trajectory", None)
    if "version" in data:
        version = data["version"]
        if type(version) is not int or version != SCHEMA_VERSION:
            raise TrajectoryError(
                "schema",
                f"version: unsupported trajectory schema version {version!r} "
                f"(this daemon reads {SCHEMA_VERSION})",
                field="version",
            )
    raw = data["waypoints"]
    if not isinstance(raw, list | tuple):
        raise TrajectoryError(
            "schema", f"waypoints: expected a list, got {_kind(raw)}", field="waypoints"
        )
    if len(raw) > limits.max_waypoints:
        raise TrajectoryError(
            "max_waypoints",
            f"{len(raw)} waypoints exceed the limit of {limits.max_waypoints}",
            value=float(len(raw)),
            field="waypoints",
        )
    return Trajectory([_waypoint(item, i, limits.unit_tolerance) for i, item in enumerate(raw)])


def _waypoint(item: Any, i: int, unit_tolerance: float) -> Waypoint:
    where = f"waypoints[{i}]"
    _keys(item, ("t", "position", "quaternion"), ("twist", "accel"), where, i)
    t = _number(item["t"], f"{where}.t", i)
    position = _vec3(item["position"], f"{where}.position", i)
    quaternion = _quaternion(item["quaternion"], f"{where}.quaternion", i, unit_tolerance)
    rates = [
        None if item.get(name) is None else _six(item[name], f"{where}.{name}", i)
        for name in ("twist", "accel")
    ]
    return Waypoint(t, Pose(position, quaternion), *rates)


def _keys(
    obj: Any, required: tuple[str, ...], optional: tuple[str, ...], where: str, i: int | None
) -> None:
    """obj is a mapping with every required key and nothing unknown."""
    if not isinstance(obj, dict):
        raise TrajectoryError(
            "schema", f"{where}: expected an object, got {_kind(obj)}", waypoint=i, field=where
        )
    unknown = sorted(repr(k) for k in obj if k not in required and k not in optional)
    if unknown:
        raise TrajectoryError(
            "schema",
            f"{where}: unknown key(s) {', '.join(unknown)} "
            f"(expected {', '.join(required + optional)})",
            waypoint=i,
            field=where,
        )
    for key in required:
        if key not in obj:
            raise TrajectoryError(
                "schema", f"{where}: missing key '{key}'", waypoint=i, field=f"{where}.{key}"
            )


def _number(x: Any, where: str, i: int) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise TrajectoryError(
            "schema", f"{where}: expected a number, got {_kind(x)}", waypoint=i, field=where
        )
    try:
        value = float(x)
    except OverflowError:  # an int beyond the float range
        value = math.inf if x > 0 else -math.inf
    if not math.isfinite(value):
        raise TrajectoryError(
            "finite",
            f"{where}: {value} is not a finite number",
            waypoint=i,
            value=value,
            field=where,
        )
    return value


def _vec3(x: Any, where: str, i: int) -> list[float]:
    """[x, y, z] or {"x": .., "y": .., "z": ..}."""
    if isinstance(x, dict):
        _keys(x, _XYZ, (), where, i)
        return [_number(x[k], f"{where}.{k}", i) for k in _XYZ]
    if not isinstance(x, list | tuple) or len(x) != 3:
        raise TrajectoryError(
            "schema",
            f"{where}: expected [x, y, z] or {{x, y, z}}, got {_kind(x)}",
            waypoint=i,
            field=where,
        )
    return [_number(c, f"{where}[{k}]", i) for k, c in enumerate(x)]


def _quaternion(x: Any, where: str, i: int, tolerance: float) -> list[float]:
    """{"w", "x", "y", "z"}, unit within `tolerance`; returned normalised."""
    if isinstance(x, list | tuple):
        raise TrajectoryError(
            "schema",
            f"{where}: a quaternion is an object {{w, x, y, z}}, never a bare array",
            waypoint=i,
            field=where,
        )
    _keys(x, _WXYZ, (), where, i)
    q = [_number(x[k], f"{where}.{k}", i) for k in _WXYZ]
    norm = math.hypot(*q)
    if not abs(norm - 1.0) <= tolerance:
        raise TrajectoryError(
            "unit_quaternion",
            f"{where} has norm {norm:.9g}; a unit quaternion (within {tolerance:g}) is required",
            waypoint=i,
            value=norm,
            field=where,
        )
    return [c / norm for c in q]


def _six(x: Any, where: str, i: int) -> list[float]:
    """{"linear": [..], "angular": [..]} -> (linear, angular) as 6 numbers."""
    _keys(x, ("linear", "angular"), (), where, i)
    return _vec3(x["linear"], f"{where}.linear", i) + _vec3(x["angular"], f"{where}.angular", i)


def _kind(x: Any) -> str:
    return "null" if x is None else type(x).__name__
