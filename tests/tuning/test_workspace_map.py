"""The workspace map against the checks it vectorises: every point's verdict is the one
the runtime's scalar pose limits (box, environment planes and boxes), the cable lengths,
the interference check and the capacity margin give at that pose; the saved file reads
back as written and knows what it was computed from."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr import Pose, Robot
from cdpr.body import Box, Environment, Plane
from cdpr.pose_limits import PoseLimits
from cdpr.so3 import quat_to_matrix
from cdpr.workspace_check import WorkspaceCheck, place
from cdpr.workspace_map import (
    BOX,
    ENVIRONMENT,
    IN,
    INTERFERENCE,
    LENGTH,
    MapSettings,
    WorkspaceMap,
    fingerprint,
    shell,
)
from tests.conftest import load_robot
from tuning.workspace_map import compute_map, orientations, plot_slices

SETTINGS = MapSettings(step=0.15, tilt=0.25, payload=(0.0, 4.0), margin=5.0)


@pytest.fixture(scope="module")
def scene(offset8: Robot) -> tuple[Robot, np.ndarray, np.ndarray, Environment]:
    """reference8-offset (its crossed pairs clear untilted) beside a wall and a table."""
    anchors = offset8.geometry.anchors
    environment = Environment(
        (Plane("wall", (-1.0, 0.0, 0.0), -1.1),),  # free side x <= 1.1
        (Box("table", (-1.4, -1.4, 0.0), (-0.6, -0.6, 0.9)),),
        tuple(tuple(a) for a in anchors.tolist()),
    )
    return offset8, anchors.min(axis=0), anchors.max(axis=0), environment


@pytest.fixture(scope="module")
def workspace(scene) -> WorkspaceMap:
    robot, lo, hi, environment = scene
    return compute_map(robot, lo, hi, environment, SETTINGS)


def test_every_point_has_the_verdict_of_the_scalar_checks(scene, workspace) -> None:
    robot, lo, hi, environment = scene
    limits = PoseLimits(
        tuple(lo), tuple(hi), robot.home.quaternion_tuple, np.pi, body=robot.body,
        environment=environment,
    )  # fmt: skip
    check = WorkspaceCheck.of(robot, margin=SETTINGS.margin)
    positions = workspace.positions().reshape(-1, 3)
    rng = np.random.default_rng(0)
    seen = set()
    for o, q in enumerate(workspace.quaternions):
        R = quat_to_matrix(q)
        reasons = workspace.reason[o].reshape(-1)
        margins = workspace.margin[o].reshape(-1)
        for i in rng.choice(len(positions), 400, replace=False):
            pose = Pose(positions[i], q)
            bad = limits.violation(pose)
            if bad is not None:
                expected = ENVIRONMENT if bad.limit == "environment" else BOX
                assert reasons[i] == expected, (o, positions[i], bad)
                seen.add(expected)
                continue
            placed = place(robot, positions[i][None], R)
            lengths = placed.lengths[0]
            if np.any(lengths < robot.length_min) or np.any(lengths > robot.length_max):
                assert reasons[i] == LENGTH
                seen.add(LENGTH)
                continue
            if check.touches.first(placed.starts[0], placed.ends[0], R) is not None:
                assert reasons[i] == INTERFERENCE
                seen.add(INTERFERENCE)
                continue
            assert reasons[i] == IN
            worst = min(check.margins(placed), check.margins(placed, payload=4.0))[0]
            assert margins[i] == pytest.approx(worst, abs=1e-3)
            seen.add(IN)
    assert {BOX, ENVIRONMENT, INTERFERENCE, IN} <= seen


def test_the_saved_map_reads_back_as_written(workspace, tmp_path) -> None:
    path = tmp_path / "reference8.workspace"
    workspace.save(path)
    back = WorkspaceMap.load(path)
    assert back.fingerprint == workspace.fingerprint and back.settings == workspace.settings
    np.testing.assert_array_equal(back.reason, workspace.reason)
    computed = workspace.reason == IN
    np.testing.assert_allclose(back.margin[computed], workspace.margin[computed], atol=0.051)
    assert np.isnan(back.margin[~computed]).all()
    assert back.summary()["volume_per_orientation_m3"] == pytest.approx(
        workspace.summary()["volume_per_orientation_m3"], rel=0.01
    )


def test_a_file_that_is_no_map_is_refused_naming_it(tmp_path) -> None:
    path = tmp_path / "junk.workspace"
    path.write_bytes(b"\x05\x00\x00\x00hello")
    with pytest.raises(ValueError, match=r"junk\.workspace: not a workspace map"):
        WorkspaceMap.load(path)


def test_the_fingerprint_follows_the_robot_the_box_the_environment_and_settings(scene) -> None:
    robot, lo, hi, environment = scene
    base = fingerprint(robot, lo, hi, environment, SETTINGS)
    assert fingerprint(robot, lo, hi, environment, SETTINGS) == base
    moved = robot.spec.model_dump()
    moved["cables"][0]["anchor"] = [1.5, 1.5, 2.49]
    assert fingerprint(Robot.from_dict(moved), lo, hi, environment, SETTINGS) != base
    assert fingerprint(robot, lo, hi + 0.1, environment, SETTINGS) != base
    assert fingerprint(robot, lo, hi, Environment(), SETTINGS) != base
    other = MapSettings(step=0.1, tilt=0.25, payload=(0.0, 4.0), margin=5.0)
    assert fingerprint(robot, lo, hi, environment, other) != base


def test_the_orientations_are_home_and_eight_tilts(reference8: Robot) -> None:
    quats = orientations(reference8.home.quaternion_tuple, 0.3)
    assert len(quats) == 9 and np.allclose(quats[0], reference8.home.quaternion)
    angles = [2 * np.arccos(min(1.0, abs(q[0]))) for q in quats[1:]]
    assert np.allclose(angles, 0.3)
    assert len(orientations(reference8.home.quaternion_tuple, 0.0)) == 1


def test_the_boundary_and_the_slices_are_drawn(workspace, tmp_path) -> None:
    positions, margins = shell(workspace, 0, limit=300)
    assert 0 < len(positions) <= 300 and np.all(margins >= SETTINGS.margin)
    path = tmp_path / "slices.png"
    plot_slices(workspace, path, "reference8")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # over 4.5 s of the default run's 10 minutes
def test_a_pulley_robot_s_map_has_the_scalar_verdicts_too() -> None:
    """suspended6's cables leave pulleys (their leave points from numpy, the rest in the
    compiled pass): every point past the box has the lengths', the interference's and
    the margin's verdict at that pose."""
    robot = load_robot("suspended6")
    anchors = robot.geometry.anchors
    lo, hi = anchors.min(axis=0) - [0, 0, 2.0], anchors.max(axis=0)
    settings = MapSettings(step=0.2, tilt=0.1, payload=(0.0, 1.0), margin=0.0)
    workspace = compute_map(robot, lo, hi, Environment(), settings)
    check = WorkspaceCheck.of(robot)
    positions = workspace.positions().reshape(-1, 3)
    seen = set()
    for o, q in enumerate(workspace.quaternions):
        R = quat_to_matrix(q)
        reasons = workspace.reason[o].reshape(-1)
        margins = workspace.margin[o].reshape(-1)
        for i in np.flatnonzero(reasons != BOX):
            placed = place(robot, positions[i][None], R)
            lengths = placed.lengths[0]
            if np.any(lengths < robot.length_min) or np.any(lengths > robot.length_max):
                expected = LENGTH
            elif check.touches.first(placed.starts[0], placed.ends[0], R) is not None:
                expected = INTERFERENCE
            else:
                expected = IN
                worst = min(check.margins(placed), check.margins(placed, payload=1.0))[0]
                assert margins[i] == pytest.approx(worst, abs=1e-3)
            assert reasons[i] == expected
            seen.add(expected)
    assert {IN, LENGTH} <= seen
