"""How the robot is drawn, the same for every viewer: the live view and its recording
(daemon.process.scene, Foxglove) and RViz (daemon.interface.ros2_model, urdf): the
colours, each cable's colour and width by its tension and its drive's fault, the
attachment points at a pose, the box round the platform's body."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Any

import numpy as np

from cdpr import Pose, Robot

SLACK_COLOR = (0.6, 0.6, 0.6, 0.8)
FAULT_COLOR = (1.0, 0.0, 1.0, 1.0)
PLATFORM_COLOR = (0.9, 0.5, 0.1, 0.9)
ANCHOR_COLOR = (0.1, 0.1, 0.1, 1.0)
#: tension / force_max -> colour: blue (none), yellow (half), red (the drive's limit)
TENSION_STOPS = ((0.0, (0.15, 0.35, 1.0)), (0.5, (1.0, 0.85, 0.1)), (1.0, (1.0, 0.1, 0.0)))
CABLE_WIDTH = 0.008  # m
SLACK_WIDTH = 0.003
MIN_BOX = 0.02  # m: the platform box's smallest side (a flat or point platform)


def tension_color(fraction: float) -> tuple[float, float, float, float]:
    """The colour of a taut cable at `fraction` of its drive's force limit (clipped)."""
    f = min(max(fraction, 0.0), 1.0) if np.isfinite(fraction) else 1.0
    for (f0, c0), (f1, c1) in pairwise(TENSION_STOPS):
        if f <= f1:
            w = (f - f0) / (f1 - f0)
            r, g, b = (a + w * (z - a) for a, z in zip(c0, c1, strict=True))
            return (r, g, b, 1.0)
    raise AssertionError("unreachable: the stops end at 1")


RGBA = tuple[float, float, float, float]


def cable_styles(
    robot: Robot, tensions: Sequence[float], faults: Sequence[str | None] = ()
) -> list[tuple[RGBA, float, str | None]]:
    """Each cable's colour, line width (m) and label (None for a taut one): a faulted
    cable magenta, a slack one (Robot.slack: below its t_min) grey and thinner, a taut
    one coloured by tension_color of its tension over its drive's force_max."""
    t = np.asarray(tensions, dtype=float)
    slack = robot.slack(t)
    styles: list[tuple[RGBA, float, str | None]] = []
    for k in range(robot.n_cables):
        fault = faults[k] if k < len(faults) else None
        if fault:
            styles.append((FAULT_COLOR, CABLE_WIDTH, f"cable {k}: {fault}"))
        elif slack[k]:
            styles.append((SLACK_COLOR, SLACK_WIDTH, f"cable {k} slack"))
        else:
            styles.append((tension_color(t[k] / robot.force_max[k]), CABLE_WIDTH, None))
    return styles


def attachments_at(
    attachments: np.ndarray, position: Sequence[float], quaternion: Sequence[float]
) -> np.ndarray:
    """The attachment points (platform frame, n x 3) in the world at the pose (n x 3)."""
    pose = Pose(position, quaternion)
    return pose.position + attachments @ pose.rotation.T


def platform_box(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The centre (platform frame) and size of the axis-aligned box round the platform's
    body: its corners, i.e. the attachment points and the robot file's body if it gives
    one; MIN_BOX at least a side (a flat or point platform)."""
    points = robot.body.points
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2.0, np.maximum(hi - lo, MIN_BOX)


def cable_faults(state: Mapping[str, Any], n: int) -> tuple[str | None, ...]:
    """Each cable's drive fault (None if none) from a state snapshot's "drives"."""
    drives = list(state.get("drives") or ())[:n]
    faults = [d.get("fault") or None if isinstance(d, Mapping) else None for d in drives]
    return tuple(faults + [None] * (n - len(faults)))
