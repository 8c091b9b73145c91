"""The platform as a body and the environment (cdpr.body, cdpr.pose_limits): every corner
inside the workspace box, clear of planes and boxes, and the cables clear of the boxes;
the separating axis test checked against a dense sampling of the body."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cdpr import Pose, Robot
from cdpr.body import Box, Environment, Plane, PlatformBody, crossed, segment_meets
from cdpr.pose_limits import PoseLimits
from cdpr.so3 import exp_so3
from cdpr.trajectory import Trajectory, TrajectoryError, TrajectoryLimits, Waypoint, validate
from tests.conftest import load_robot

LIMITS = TrajectoryLimits()


@pytest.fixture(scope="module")
def reference8() -> Robot:
    return load_robot("reference8")


def _limits(robot: Robot, environment: Environment | None = None) -> PoseLimits:
    anchors = robot.geometry.anchors
    return PoseLimits(
        tuple(anchors.min(axis=0).tolist()),
        tuple(anchors.max(axis=0).tolist()),
        robot.home.quaternion_tuple,
        0.6,
        body=robot.body,
        environment=environment or Environment(),
    )


def _environment(robot: Robot, planes=(), boxes=()) -> Environment:
    anchors = tuple(tuple(a) for a in robot.geometry.anchors.tolist())
    return Environment(tuple(planes), tuple(boxes), anchors)


def test_the_body_is_the_attachments_hull_by_default_and_the_file_can_add_to_it() -> None:
    robot = load_robot("reference8")
    assert len(robot.body.corners) == 8 and robot.body.attachment_of == tuple(range(8))
    suspended = load_robot("suspended6")  # three attachment points, each shared by two cables
    assert len(suspended.body.corners) == 3
    assert suspended.body.attachment_of == (0, 1, 1, 2, 2, 0)
    data = robot.spec.model_dump()
    data["platform"]["body"] = {"box": {"min": [-0.25, -0.25, -0.4], "max": [0.25, 0.25, 0.3]}}
    boxed = Robot.from_dict(data)
    # the box's 8 corners, and the attachments that are not among them
    assert len(boxed.body.corners) == 16 and min(boxed.body.points[:, 2]) == -0.4


def test_a_reference_point_inside_the_box_with_the_corners_below_the_floor_is_refused(
    reference8: Robot,
) -> None:
    """The case found: p at z = 0.10 m is inside the box (z >= 0), the platform's lower
    corners at z = -0.2 m are not; the violation names the corner."""
    limits = _limits(reference8)
    low = Pose((0.0, 0.0, 0.10))
    bad = limits.violation(low)
    assert bad is not None and bad.limit == "workspace_min"
    assert bad.detail.startswith("platform corner 1 (0.2, -0.2, -0.3 m in the platform frame)")
    assert "at z = -0.2000 m outside [0.0000, 2.5000] m" in bad.detail
    assert bad.value == pytest.approx(-0.2)
    assert limits.violation(Pose((0.0, 0.0, 0.31))) is None


def test_a_turned_platform_is_held_by_its_corners(reference8: Robot) -> None:
    """Turned 30 deg about y at x = 1.25, the reference point is 0.25 m inside the
    +x face; a corner is outside it."""
    limits = _limits(reference8)
    turned = Pose.from_rotvec((1.25, 0.0, 1.25), (0.0, np.radians(30.0), 0.0))
    bad = limits.violation(turned)
    assert bad is not None and bad.limit == "workspace_max" and "platform corner" in bad.detail
    assert limits.violation(Pose((1.25, 0.0, 1.25))) is None


def test_a_corner_behind_a_plane_is_named_with_the_plane(reference8: Robot) -> None:
    wall = Plane("wall", (-1.0, 0.0, 0.0), -1.0)  # free side x <= 1.0
    limits = _limits(reference8, _environment(reference8, planes=[wall]))
    bad = limits.violation(Pose((0.9, 0.0, 1.25)))
    assert bad is not None and bad.limit == "environment"
    assert "platform corner 0 (" in bad.detail
    assert "lies 0.1000 m behind plane 'wall'" in bad.detail
    assert limits.violation(Pose((0.75, 0.0, 1.25))) is None
    # with margins, a corner within them of the wall is refused, saying so
    inner = limits.shrunk(0.02, 0.05)
    near = inner.violation(Pose((0.79, 0.0, 1.25)))
    assert near is not None and "in front of plane 'wall', within the margin" in near.detail


def test_a_box_crossed_by_a_cable_alone_is_refused_naming_the_cable(reference8: Robot) -> None:
    """A small box on the line of cable 1 (from the floor anchor at (1.5, 1.5, 0) to its
    corner): no corner of the platform near it, the cable through it."""
    anchor = reference8.geometry.anchors[1]
    corner = reference8.home.position + reference8.geometry.attachments[1]
    middle = (anchor + corner) / 2.0
    box = Box("crate", tuple((middle - 0.05).tolist()), tuple((middle + 0.05).tolist()))
    limits = _limits(reference8, _environment(reference8, boxes=[box]))
    bad = limits.violation(reference8.home)
    assert bad is not None and bad.limit == "environment"
    assert bad.detail == "cable 1 crosses box 'crate'"


def test_a_trajectory_through_a_box_names_the_waypoint_the_cable_and_the_box(
    reference8: Robot,
) -> None:
    """A table under the +x side of the frame: the platform clears it at (0.5, 0, 0.75),
    the lower cable from the anchor at (1.5, 1.5, 0) runs through it there."""
    table = Box("table", (0.9, -0.5, 0.0), (1.5, 0.5, 0.6))
    limits = _limits(reference8, _environment(reference8, boxes=[table])).shrunk(0.02, 0.05)
    home = reference8.home
    assert limits.violation(home) is None
    trajectory = Trajectory(
        [
            Waypoint(0.0, home),
            Waypoint(3.0, Pose(home.position + np.array([0.5, 0.0, -0.5]))),
            Waypoint(6.0, home),
        ]
    )
    with pytest.raises(TrajectoryError) as info:
        validate(trajectory, reference8, LIMITS, pose_limits=limits)
    err = info.value
    assert (err.limit, err.waypoint) == ("environment", 1)
    assert str(err).startswith("waypoint 1: environment: cable 1 crosses box 'table' (")


def test_the_body_crossing_a_box_with_no_corner_inside_is_found(reference8: Robot) -> None:
    """A thin post pokes up into the middle of the platform's bottom face: no corner of
    either is inside the other, the separating axis test finds the overlap."""
    post = Box("post", (-0.02, -0.02, 0.0), (0.02, 0.02, 1.0))
    limits = _limits(reference8, _environment(reference8, boxes=[post]))
    bad = limits.violation(reference8.home)  # the bottom face at z = 0.95
    assert bad is not None and bad.detail == "the platform body crosses box 'post'"
    assert limits.violation(Pose(reference8.home.position + np.array([0.0, 0.0, 0.1]))) is None


@settings(max_examples=150, deadline=None)
@given(
    position=st.tuples(*[st.floats(-0.6, 0.6)] * 3),
    rotvec=st.tuples(*[st.floats(-2.0, 2.0)] * 3),
    size=st.tuples(*[st.floats(0.02, 0.5)] * 3),
)
def test_the_separating_axis_test_agrees_with_a_dense_sampling(position, rotvec, size) -> None:
    """Against the points of a fine grid over the body (a 0.4 x 0.4 x 0.6 box): a box with
    a grid point inside is met; one the test calls met is within a grid step of a point."""
    corners = [(x, y, z) for x in (-0.2, 0.2) for y in (-0.2, 0.2) for z in (-0.3, 0.3)]
    body = PlatformBody(corners, corners)
    rotation = exp_so3(np.array(rotvec))
    world = body.world(rotation, np.zeros(3))
    centre, half = np.array(position), np.array(size) / 2.0
    box = Box("b", tuple((centre - half).tolist()), tuple((centre + half).tolist()))
    grid = np.stack(
        np.meshgrid(*[np.linspace(-a, a, 9) for a in (0.2, 0.2, 0.3)], indexing="ij"), -1
    ).reshape(-1, 3)
    points = grid.dot(rotation.T)
    step = 0.3 / 8 * np.sqrt(3.0)  # the farthest a body point lies from a grid point
    inside = np.all((points >= box.lower) & (points <= box.upper), axis=1).any()
    met = body.meets(world, rotation, box, 0.0)
    if inside:
        assert met
    if met:
        low, high = np.array(box.lower) - step, np.array(box.upper) + step
        assert np.all((points >= low) & (points <= high), axis=1).any()


def test_the_slab_test_on_segments() -> None:
    lower, upper = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    grown = (-0.1, -0.1, -0.1), (1.1, 1.1, 1.1)
    cases = [  # start, end, meets the box, meets it grown by 0.1
        ((-1.0, 0.5, 0.5), (2.0, 0.5, 0.5), True, True),  # through it
        ((-1.0, 2.0, 0.5), (2.0, 2.0, 0.5), False, False),  # beside it, parallel to a face
        ((0.5, 0.5, 2.0), (0.5, 0.5, 1.5), False, False),  # ends short of it
        ((2.0, 2.0, 2.0), (1.05, 1.05, 1.05), False, True),  # ends near a corner
        ((0.5, 0.5, 0.5), (0.6, 0.6, 0.6), True, True),  # inside it
    ]
    for start, end, meets, near in cases:
        assert segment_meets(start, end, lower, upper) is meets, (start, end)
        assert segment_meets(start, end, *grown) is near, (start, end)
        assert segment_meets(end, start, lower, upper) is meets, (end, start)


def test_crossed_checks_nothing_without_obstacles(reference8: Robot) -> None:
    home = reference8.home
    corners = reference8.body.placed(home)
    assert np.allclose(corners, reference8.body.world(home.rotation, home.position))
    assert crossed(reference8.body, _environment(reference8), home, corners, 0.0, 0.0) is None
