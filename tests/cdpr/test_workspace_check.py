"""Validation holds every sampled reference to the workspace: the capacity margin with the
platform's current mass, and no cable interference; the refusal names the waypoint, the
limit and the cables.  The poses are reference8-offset's (tests/data/robots), inside
every other limit (pose limits with their margins, cable lengths, the wrench at rest in W)."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import Pose, Robot
from cdpr.trajectory import (
    Reference,
    Trajectory,
    TrajectoryError,
    TrajectoryLimits,
    Waypoint,
    goto,
    validate,
)
from cdpr.trajectory.limits import BatchRefusal
from cdpr.workspace_check import WorkspaceCheck, place

LIMITS = TrajectoryLimits()
# at home orientation near the top: 4.3 N of margin (cables 0, 5, 7 at their bounds)
THIN = Pose((0.1, 0.316, 1.927))
# tilted 0.2 rad near home: the crossed cables 0 and 6 pass 0.2 mm apart
CROSSED = Pose.from_rotvec((0.076, -0.043, 1.208), (0.042, 0.141, 0.136))


def _at_rest(pose: Pose) -> Reference:
    return Reference(pose, np.zeros(6), np.zeros(6))


def _refusal(robot: Robot, check: WorkspaceCheck, target: Pose) -> TrajectoryError:
    trajectory = goto(_at_rest(robot.home), target, LIMITS)
    with pytest.raises(TrajectoryError) as refused:
        validate(trajectory, robot, LIMITS, workspace=check)
    return refused.value


def test_a_goto_to_a_pose_with_too_little_margin_is_refused_naming_the_cables(
    offset8: Robot,
) -> None:
    check = WorkspaceCheck.of(offset8, margin=5.0)
    err = _refusal(offset8, check, THIN)
    assert err.limit == "workspace.margin"
    assert err.waypoint == 0  # a goto: one segment
    assert "N inside what the cables can give (cable 0 at force_max" in str(err)
    assert "less than workspace.margin 5 N at t=" in str(err)
    # with less asked of it, the same goto is accepted
    lenient = WorkspaceCheck.of(offset8, margin=4.0)
    validate(goto(_at_rest(offset8.home), THIN, LIMITS), offset8, LIMITS, workspace=lenient)


def test_a_goto_where_two_cables_touch_is_refused_naming_them(offset8: Robot) -> None:
    check = WorkspaceCheck.of(offset8, margin=0.0)
    err = _refusal(offset8, check, CROSSED)
    assert err.limit == "workspace.interference"
    assert "cables 0 and 6 pass" in str(err) and "closer than their diameters allow" in str(err)
    # without the interference check the same goto passes
    validate(
        goto(_at_rest(offset8.home), CROSSED, LIMITS),
        offset8,
        LIMITS,
        workspace=WorkspaceCheck.of(offset8, margin=0.0, interference=False),
    )


def test_the_margin_follows_the_payload_estimate(offset8: Robot) -> None:
    """A pose with 20 N of margin for the file's 10 kg platform has less with 5 kg more:
    the check carrying the estimate refuses it where the file's accepts it."""
    check = WorkspaceCheck.of(offset8, margin=5.0)
    pose = Pose((0.1, 0.3, 1.85))
    here = place(offset8, pose.position[None], pose.rotation)
    light = check.margins(here)[0]
    heavy = check.carrying(15.0, (0.0, 0.0, -0.02))
    loaded = heavy.margins(here)[0]
    assert loaded < light
    assert loaded == pytest.approx(check.margins(here, payload=5.0)[0])
    threshold = (light + loaded) / 2.0
    assert (
        WorkspaceCheck.of(offset8, margin=threshold).first_refusal(
            pose.position[None], pose.rotation
        )
        is None
    )
    refused = WorkspaceCheck.of(offset8, margin=threshold).carrying(15.0, (0, 0, -0.02))
    found = refused.first_refusal(pose.position[None], pose.rotation)
    assert found is not None and "15 kg platform" in found.detail


def test_only_the_first_failing_sample_of_a_batch_is_reported(offset8: Robot) -> None:
    check = WorkspaceCheck.of(offset8, margin=5.0)
    poses = [offset8.home, THIN, CROSSED, offset8.home]
    positions = np.array([p.position for p in poses])
    rotations = np.array([p.rotation for p in poses])
    found = check.first_refusal(positions, rotations)
    assert found is not None and found.index == 1 and found.limit == "workspace.margin"
    found = check.first_refusal(positions[2:], rotations[2:])
    assert found is not None and found.index == 0 and found.limit == "workspace.interference"
    assert check.first_refusal(positions[3:], rotations[3:]) is None


def test_the_waypoint_named_is_the_segment_holding_the_failing_sample(offset8: Robot) -> None:
    home = offset8.home
    trajectory_points = [
        Waypoint(0.0, home),
        Waypoint(2.0, Pose((0.0, 0.0, 1.4))),
        Waypoint(4.0, Pose((0.0, 0.0, 1.25))),
        Waypoint(8.0, THIN),
    ]
    with pytest.raises(TrajectoryError) as refused:
        validate(
            Trajectory(trajectory_points),
            offset8,
            LIMITS,
            workspace=WorkspaceCheck.of(offset8, margin=5.0),
        )
    assert refused.value.waypoint == 2


class Above:
    """A BatchCheck refusing every pose above `z` (m)."""

    def __init__(self, z: float) -> None:
        self.z = z

    def first_refusal(
        self, positions: np.ndarray, rotations: np.ndarray, jacobians: np.ndarray | None = None
    ) -> BatchRefusal | None:
        high = np.flatnonzero(positions[:, 2] > self.z)
        return None if not len(high) else BatchRefusal(int(high[0]), "test.above", "too high")


def test_the_first_problem_along_the_path_is_named_whichever_check_finds_it(
    offset8: Robot,
) -> None:
    """The batch check runs on every CHUNK samples; a pose limit broken a little later
    within the same batch does not hide the earlier refusal, nor the other way round."""
    rise = goto(_at_rest(offset8.home), Pose((0.0, 0.0, 1.45)), LIMITS)

    def below(pose: Pose, twist: np.ndarray, accel: np.ndarray) -> str | None:
        return "above 1.36 m" if pose.position[2] > 1.36 else None  # checked at samples only

    for workspace, limit in ((Above(1.30), "test.above"), (Above(1.40), "wrench_set")):
        with pytest.raises(TrajectoryError) as refused:
            validate(rise, offset8, LIMITS, wrench_check=below, workspace=workspace)
        assert refused.value.limit == limit
