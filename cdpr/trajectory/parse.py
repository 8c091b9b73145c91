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
import sys
from typing import Any

import numpy as np

from cdpr.pose import Pose
from cdpr.trajectory.core import SCHEMA_VERSION, Trajectory, TrajectoryError, Waypoint
from cdpr.trajectory.limits import TrajectoryLimits

_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")
_PLAIN = {"t", "position", "quaternion"}  # the keys of a waypoint read in bulk
_QUATERNION = set(_WXYZ)
_LARGEST_INT = int(sys.float_info.max)  # larger ones overflow float()


def parse_trajectory(data: Any, limits: TrajectoryLimits | None = None) -> Trajectory:
    """Build a Trajectory from its interface form; TrajectoryError on any bad input."""
    limits = TrajectoryLimits() if limits is None else limits
    raw = items(data, "waypoints", "trajectory", limits)
    plain, values, clear = _plain(raw, limits.unit_tolerance)
    if len(plain) == len(raw) and clear.all():  # a Waypoint per waypoint spared
        return Trajectory.through(values[:, 0], values[:, 1:4], values[:, 4:])
    return Trajectory(_waypoints(raw, plain, values, clear, limits.unit_tolerance))


def items(data: Any, key: str, what: str, limits: TrajectoryLimits) -> list | tuple:
    """The list under `key` of a `what` message ("trajectory", "path"), after its keys,
    its version and its length are checked; TrajectoryError naming the problem."""
    _keys(data, (key,), ("version",), what, None)
    version = data.get("version", SCHEMA_VERSION)
    if type(version) is not int or version != SCHEMA_VERSION:
        raise TrajectoryError(
            "schema",
            f"version: unsupported {what} schema version {version!r} "
            f"(this daemon reads {SCHEMA_VERSION})",
            field="version",
        )
    raw = data[key]
    if not isinstance(raw, list | tuple):
        raise TrajectoryError("schema", f"{key}: expected a list, got {_kind(raw)}", field=key)
    if len(raw) > limits.max_waypoints:
        raise TrajectoryError(
            "max_waypoints",
            f"{len(raw)} {key} exceed the limit of {limits.max_waypoints}",
            value=float(len(raw)),
            field=key,
        )
    return raw


def _plain(raw: list[Any] | tuple[Any, ...], unit_tolerance: float) -> tuple[list[int], Any, Any]:
    """The waypoints of the plain form (t, a position list and a quaternion object,
    nothing else), read in bulk: their indices, their numbers (_plain_values) and which of
    them are clear of doubt.  The bulk read costs a tenth of _waypoint's (~2 µs a
    waypoint)."""
    plain: list[int] = []
    numbers: list[Any] = []  # t, x, y, z, w, qx, qy, qz of each plain waypoint
    for i, item in enumerate(raw):
        if type(item) is dict and item.keys() == _PLAIN:
            p, q = item["position"], item["quaternion"]
            if type(p) is list and len(p) == 3 and type(q) is dict and q.keys() == _QUATERNION:
                plain.append(i)
                numbers += (item["t"], *p, q["w"], q["x"], q["y"], q["z"])
    values, clear = _plain_values(numbers, len(plain), unit_tolerance)
    return plain, values, clear


def _waypoints(
    raw: list[Any] | tuple[Any, ...],
    plain: list[int],
    values: Any,
    clear: Any,
    unit_tolerance: float,
) -> list[Waypoint]:
    """The waypoints: the plain ones clear of doubt from their bulk-read `values`
    (_plain), one by one by _waypoint otherwise.

    Every waypoint of another form, and every plain one whose numbers the bulk check
    doubts (not a number, not finite, a norm not clearly within the tolerance), goes to
    _waypoint in order: so the first problem is named exactly as _waypoint names it, and
    _waypoint decides every doubt.
    """
    out: list[Waypoint | None] = [None] * len(raw)
    t, positions, quaternions = values[:, 0].tolist(), values[:, 1:4], values[:, 4:]
    for k in np.flatnonzero(clear).tolist():
        pose = Pose._from_unit(positions[k].tolist(), quaternions[k].tolist())
        out[plain[k]] = Waypoint(t[k], pose)
    for i, item in enumerate(out):
        if item is None:
            out[i] = _waypoint(raw[i], i, unit_tolerance)
    return out  # type: ignore[return-value]  # each one set


def _plain_values(numbers: list[Any], n: int, unit_tolerance: float) -> tuple[Any, Any]:
    """The plain waypoints' numbers (n, 8), each quaternion normalised with its sign as
    Pose chooses it, and which of the n are clear of doubt (the others go to _waypoint)."""
    try:
        if not set(map(type, numbers)) <= {float, int}:  # bool, str, None, ...
            raise OverflowError
        values = np.array(numbers, dtype=float).reshape(n, 8)
    except OverflowError:  # or an int beyond the float range: each such number as NaN
        values = np.array([_float_or_nan(x) for x in numbers], dtype=float).reshape(n, 8)
    q = values[:, 4:]
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))
        clear = np.all(np.isfinite(values), axis=1) & (np.abs(norm - 1.0) <= 0.5 * unit_tolerance)
    q /= np.where(clear, norm, 1.0)[:, None]
    first = q[np.arange(n), np.argmax(q != 0.0, axis=1)]  # w, or the first non-zero one
    q[first < 0.0] *= -1.0
    return values, clear


def _float_or_nan(x: Any) -> float:
    """x as a float if it is a number (bool is not) within the float range, else NaN."""
    if type(x) is float:
        return x
    if type(x) is int and abs(x) <= _LARGEST_INT:
        return float(x)
    return math.nan


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
