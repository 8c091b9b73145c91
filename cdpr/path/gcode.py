"""G-code to a path, for `cdprd send --gcode` and `cdprd plan`: the subset a cable robot
moving a tool or a camera needs, read as Klipper and Marlin read it.

    G0 / G1 X Y Z F   move (modal); F: feed, units per minute, a speed cap on G1 moves
                      (G0 moves at trajectory.linear_speed); axes left out keep their value
    G4 P<ms> | S<s>   dwell at rest
    G20 / G21         inches / millimetres (the default)
    G90 / G91         absolute (the default) / relative coordinates
    N<n>              line numbers (ignored); ; and ( ) comments; % lines

Coordinates are the world frame's (m = 1000 mm); the orientation stays the start's.  Any
other word (M3, T1, E, A, G2, G28, ...) is refused naming its line, as is a move before
G0/G1 was given, a number that is not one, or a program that moves nowhere.
"""

from __future__ import annotations

import math
import re

from cdpr.path.model import Path, PathPoint
from cdpr.pose import Pose
from cdpr.trajectory.core import TrajectoryError
from cdpr.trajectory.limits import TrajectoryLimits

_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_UNITS = {20: 0.0254, 21: 0.001}  # m per unit
_MOTION = (0, 1)
_SETTINGS = (4, 20, 21, 90, 91)


def parse_gcode(
    text: str, start: Pose, blend: float = 0.0, limits: TrajectoryLimits | None = None
) -> Path:
    """The path from `start` through every move of `text` (module docstring), each corner
    rounded by `blend` (m); TrajectoryError naming the line of the first problem."""
    limits = TrajectoryLimits() if limits is None else limits
    position = start.position_tuple
    points = [PathPoint(start)]
    scale, relative, motion, feed = _UNITS[21], False, None, None
    for number, raw in enumerate(text.splitlines(), start=1):
        words = _words(raw, number)
        codes = [int(value) for letter, value in words if letter == "G"]
        axes = {letter: value for letter, value in words if letter in "XYZ"}
        values = {letter: value for letter, value in words if letter in "FPS"}
        for code in codes:
            if code in _MOTION:
                motion = code
            elif code in _UNITS:
                scale = _UNITS[code]
            elif code in (90, 91):
                relative = code == 91
        if "F" in values:
            feed = _positive(values["F"], "F", number) * scale / 60.0
        if 4 in codes:
            seconds = values.get("P", 0.0) / 1000.0 + values.get("S", 0.0)
            last = points[-1]
            points[-1] = PathPoint(last.pose, last.speed, last.blend, last.dwell + seconds)
            continue
        if not axes:
            continue
        if motion is None:
            move = raw.strip()
            raise TrajectoryError("gcode", f"line {number}: a move before G0 or G1: {move!r}")
        target = tuple(
            (at if relative else 0.0) + axes[axis] * scale if axis in axes else at
            for at, axis in zip(position, "XYZ", strict=True)
        )
        if target == position:
            continue
        if not all(map(math.isfinite, target)):
            raise TrajectoryError("gcode", f"line {number}: the move leaves the numbers' range")
        position = target
        speed = feed if motion == 1 else None
        # the start's orientation, already a checked unit quaternion; finite coordinates
        points.append(PathPoint(Pose._from_unit(position, start.quaternion_tuple), speed, blend))
        if len(points) > limits.max_waypoints:
            raise TrajectoryError(
                "max_waypoints", f"line {number}: more than {limits.max_waypoints} poses"
            )
    if len(points) < 2:
        raise TrajectoryError("gcode", "the program moves nowhere: no G0/G1 move")
    return Path(tuple(points))


def _words(raw: str, number: int) -> list[tuple[str, float]]:
    """The line's words (letter, value), comments and line numbers dropped; any word
    outside the subset refused."""
    line = re.sub(r"\([^)]*\)", " ", raw.split(";", 1)[0]).strip()
    if line in ("", "%"):
        return []
    words, rest = [], line
    for match in _WORD.finditer(line):
        words.append((match.group(1).upper(), float(match.group(2))))
        rest = rest.replace(match.group(0), " ", 1)
    if rest.strip():
        unread, whole = rest.strip(), raw.strip()
        raise TrajectoryError("gcode", f"line {number}: cannot read {unread!r} in {whole!r}")
    out = []
    for letter, value in words:
        if letter == "N":
            continue
        if letter == "G" and value in (*_MOTION, *_SETTINGS):
            out.append((letter, value))
        elif letter in "XYZFPS":
            if not math.isfinite(value):
                raise TrajectoryError("gcode", f"line {number}: {letter}{value} is not a number")
            out.append((letter, value))
        else:
            code = f"{letter}{value:g}"
            raise TrajectoryError(
                "gcode",
                f"line {number}: {code} is not supported (G0/G1 X Y Z F, G4 P|S, G20/G21, G90/G91)",
            )
    return out


def _positive(value: float, letter: str, number: int) -> float:
    if not value > 0.0:
        raise TrajectoryError("gcode", f"line {number}: {letter}{value:g} must be positive")
    return value
