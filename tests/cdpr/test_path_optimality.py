"""The path timing against an independent convex formulation (tuning.convex_timing:
Verscheure et al. 2009, the tensions themselves as variables, not cdpr.path.timing's
facets; a second-order cone program on a grid 10 times finer): TOPP-RA's duration within
3 % of its optimum."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from cdpr.path import Path, PathPoint
from cdpr.path.timing import Timing, time_path
from cdpr.pose import Pose
from cdpr.trajectory import TrajectoryLimits
from tests.daemon_stack import config_for
from tuning.convex_timing import convex_duration

MARGIN = 5.0  # N inside the tension range, in both


@pytest.fixture(scope="module")
def undamped():
    """reference8 with the winches' damping at 0: the timing takes it at a first pass's
    speed (a fixed force), which no convex formulation in (a, b) can hold; without it
    both solve the same problem."""
    robot = copy.deepcopy(config_for("cia402").robot)
    robot.k0 = np.zeros_like(robot.k0)
    return robot


@pytest.mark.slow  # ~35 s: 600 grid points of eight tensions each
@pytest.mark.parametrize(
    ("name", "poses", "blends", "limits"),
    [
        (
            "fast lift, the tensions bind",
            [Pose([0.0, 0.0, 1.0], [1, 0, 0, 0]), Pose([0.0, 0.0, 1.6], [1, 0, 0, 0])],
            [0.0, 0.0],
            TrajectoryLimits(linear_speed=20.0, linear_accel=200.0, angular_accel=500.0),
        ),
        (
            "blended corner at the default limits",
            [
                Pose([0.0, 0.0, 1.25], [1, 0, 0, 0]),
                Pose([0.3, 0.0, 1.25], [1, 0, 0, 0]),
                Pose([0.3, 0.3, 1.35], [1, 0, 0, 0]),
            ],
            [0.0, 0.05, 0.0],
            TrajectoryLimits(),
        ),
    ],
)
def test_the_timing_is_within_3_percent_of_the_convex_optimum(
    undamped, name: str, poses, blends, limits
) -> None:
    timing = Timing(margin=MARGIN, step=0.01)
    path = Path(tuple(PathPoint(p, blend=r) for p, r in zip(poses, blends, strict=True)))
    planned = time_path(path, undamped, limits, timing).duration
    optimum = convex_duration(poses, blends, undamped, limits, MARGIN, step=0.001)
    ratio = planned / optimum
    print(f"{name}: TOPP-RA {planned:.4f} s, convex optimum {optimum:.4f} s, ratio {ratio:.4f}")
    assert 0.99 <= ratio <= 1.03
