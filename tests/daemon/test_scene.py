"""The scene in Foxglove's standard schemas (daemon.process.scene), decoded the way a
Foxglove client decodes it (by the advertised protobuf schema): cables from the model's
anchors to its attachment points at the pose, coloured by tension, slack and faulted
cables marked, the platform and the reference as boxes, the frame transforms, and
events as foxglove.Log."""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from cdpr import Pose, Robot
from daemon.interface.robot_drawing import FAULT_COLOR, SLACK_COLOR, cable_faults, tension_color
from daemon.process.recording import CycleRecord
from daemon.process.scene import (
    LOG_TOPIC,
    POSE_TOPIC,
    REFERENCE_POSE_TOPIC,
    SCENE_TOPIC,
    SERIES_SCHEMA,
    SERIES_TOPIC,
    TF_TOPIC,
    SceneBuilder,
    standard_channels,
    timing_figures,
)
from tests.foxglove_client import decoder

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "reference8.yaml"
STAMP = 1_700_000_000_123_456_789
POSE = Pose((0.1, -0.05, 1.3), (np.cos(0.1), 0.0, np.sin(0.1), 0.0))  # tilted 0.2 rad about y
REFERENCE = Pose((0.12, -0.04, 1.31), (1.0, 0.0, 0.0, 0.0))
LO, HI = (-1.0, -1.0, 0.2), (1.0, 1.0, 2.2)


@pytest.fixture(scope="module")
def robot() -> Robot:
    return Robot.from_yaml(ROBOT)


def _record(robot: Robot, tensions: list[float], reference: Pose | None = REFERENCE):
    return CycleRecord(
        t=2.5,
        position=POSE.position_tuple,
        quaternion=POSE.quaternion_tuple,
        twist=[0.0] * 6,
        lengths=robot.cable_lengths(POSE).tolist(),
        tensions=tensions,
        forces=[-t for t in tensions],
        safety="tracking",
        reference=None
        if reference is None
        else (reference.position_tuple, reference.quaternion_tuple),
    )


def _decoded(messages: list[tuple[str, bytes]]) -> dict:
    specs = {spec.topic: spec for spec in standard_channels()}
    out = {}
    for topic, data in messages:
        spec = specs[topic]
        decode = decoder(
            spec.message_encoding, spec.schema_name, spec.schema_encoding, spec.schema_data
        )
        out[topic] = decode(data)
    return out


def _rgba(color) -> tuple[float, ...]:
    return (color.r, color.g, color.b, color.a)


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def _entity(scene, ident: str):
    (entity,) = [e for e in scene.entities if e.id == ident]
    return entity


def test_the_channels_carry_foxglove_standard_schemas() -> None:
    names = {spec.topic: (spec.schema_name, spec.message_encoding) for spec in standard_channels()}
    assert names[TF_TOPIC] == ("foxglove.FrameTransforms", "protobuf")
    assert names[SCENE_TOPIC] == ("foxglove.SceneUpdate", "protobuf")
    assert names[POSE_TOPIC] == names[REFERENCE_POSE_TOPIC] == ("foxglove.PoseInFrame", "protobuf")
    assert names[LOG_TOPIC] == ("foxglove.Log", "protobuf")
    assert names[SERIES_TOPIC] == ("cdprd.Series", "json")


def test_cables_run_from_the_anchors_to_the_attachment_points_coloured_by_tension(
    robot: Robot,
) -> None:
    n = robot.n_cables
    tensions = [50.0, 100.0, 200.0, 300.0, 450.0, 550.0, 0.0, 10.0]  # 6: none, 7: < t_min
    faults = [None] * n
    faults[3] = "drive fault 0x2310"
    builder = SceneBuilder(robot, (LO, HI))
    scene = _decoded(builder.encode(_record(robot, tensions), STAMP, faults))[SCENE_TOPIC]

    cables = _entity(scene, "cables")
    assert cables.frame_id == "world"
    assert len(cables.lines) == n
    ends = POSE.position + robot.geometry.attachments @ POSE.rotation.T
    for k, line in enumerate(cables.lines):
        a, b = (_xyz(p) for p in line.points)
        assert np.allclose(a, robot.geometry.anchors[k], atol=1e-12)
        assert np.allclose(b, ends[k], atol=1e-12)

    colors = [_rgba(line.color) for line in cables.lines]
    taut = [0, 1, 2, 4, 5]
    for k in taut:
        expected = tension_color(tensions[k] / robot.force_max[k])
        assert colors[k] == pytest.approx(expected)
    blues = [colors[k][2] for k in taut]  # less blue, more red as the tension grows
    reds = [colors[k][0] for k in taut]
    assert all(b1 > b2 for b1, b2 in pairwise(blues))
    assert all(r1 <= r2 for r1, r2 in pairwise(reds)) and reds[-1] > reds[0]
    assert colors[6] == colors[7] == pytest.approx(SLACK_COLOR)
    assert colors[3] == pytest.approx(FAULT_COLOR)
    labels = sorted(text.text for text in cables.texts)
    assert labels == ["cable 3: drive fault 0x2310", "cable 6 slack", "cable 7 slack"]


def test_the_platform_the_reference_ghost_the_frame_and_the_workspace(robot: Robot) -> None:
    builder = SceneBuilder(robot, (LO, HI))
    record = _record(robot, [300.0] * robot.n_cables)
    decoded = _decoded(builder.encode(record, STAMP))
    scene = decoded[SCENE_TOPIC]

    body = robot.geometry.attachments
    centre = (body.min(axis=0) + body.max(axis=0)) / 2
    for ident, pose in (("platform", POSE), ("reference", REFERENCE)):
        (cube,) = _entity(scene, ident).cubes
        assert np.allclose(_xyz(cube.pose.position), pose.position + pose.rotation @ centre)
        q = cube.pose.orientation
        assert np.allclose([q.w, q.x, q.y, q.z], pose.quaternion)
        assert np.allclose(_xyz(cube.size), body.max(axis=0) - body.min(axis=0))
    ghost, solid = (_entity(scene, ident).cubes[0].color.a for ident in ("reference", "platform"))
    assert ghost < solid
    anchors = [_xyz(s.pose.position) for s in _entity(scene, "frame").spheres]
    assert np.allclose(anchors, robot.geometry.anchors)
    (box,) = _entity(scene, "workspace").cubes
    assert np.allclose(_xyz(box.size), np.subtract(HI, LO))
    assert (scene.entities[0].timestamp.seconds, scene.entities[0].timestamp.nanos) == (
        STAMP // 10**9,
        STAMP % 10**9,
    )

    transforms = {t.child_frame_id: t for t in decoded[TF_TOPIC].transforms}
    assert set(transforms) == {"platform", "reference"}
    for child, pose in (("platform", POSE), ("reference", REFERENCE)):
        assert transforms[child].parent_frame_id == "world"
        assert np.allclose(_xyz(transforms[child].translation), pose.position)
        r = transforms[child].rotation
        assert np.allclose([r.w, r.x, r.y, r.z], pose.quaternion)
    assert np.allclose(_xyz(decoded[POSE_TOPIC].pose.position), POSE.position)
    assert np.allclose(_xyz(decoded[REFERENCE_POSE_TOPIC].pose.position), REFERENCE.position)
    series = decoded[SERIES_TOPIC]
    error = np.linalg.norm(POSE.position - REFERENCE.position)
    assert series["tracking_error"]["position"] == pytest.approx(error)
    assert series["tensions"] == [300.0] * robot.n_cables


def test_without_a_reference_the_ghost_is_deleted(robot: Robot) -> None:
    builder = SceneBuilder(robot, (LO, HI))
    decoded = _decoded(builder.encode(_record(robot, [300.0] * 8, reference=None), STAMP))
    scene = decoded[SCENE_TOPIC]
    assert "reference" not in {e.id for e in scene.entities}
    assert [d.id for d in scene.deletions] == ["reference"]
    assert [t.child_frame_id for t in decoded[TF_TOPIC].transforms] == ["platform"]
    assert REFERENCE_POSE_TOPIC not in decoded
    assert decoded[SERIES_TOPIC]["tracking_error"] is None


def test_events_become_log_messages(robot: Robot) -> None:
    builder = SceneBuilder(robot, (LO, HI))
    brake = {"event": "brake", "state": "braked", "trigger": "workspace", "message": "x > 1"}
    (log,) = _decoded(builder.encode_event(brake, STAMP)).values()
    assert log.level == 4  # foxglove.Log.Level.ERROR
    assert log.message == "brake: workspace: x > 1"
    state = {"event": "state", "state": "hold", "why": "enabled"}
    (log,) = _decoded(builder.encode_event(state, STAMP)).values()
    assert (log.level, log.message) == (2, "hold: enabled")  # INFO


def test_faults_and_timing_come_from_the_state_snapshot() -> None:
    state = {
        "drives": [{"state": "operation", "fault": None}, {"state": "fault", "fault": "0x2310"}],
        "cycle": {"cycles": 10, "deadline_misses": 1, "compute": {"p99_us": 250.0}},
    }
    assert cable_faults(state, 3) == (None, "0x2310", None)
    figures = timing_figures(state["cycle"])
    assert figures == {"cycles": 10.0, "deadline_misses": 1.0, "compute_p99_us": 250.0}
    assert json.loads(json.dumps(figures)) == figures


def test_the_layout_opens_on_the_3d_view_and_plots_of_served_channels() -> None:
    layout = json.loads((ROBOT.parents[1] / "foxglove-layout.json").read_text())
    panels = []

    def walk(content: dict) -> None:
        if content["type"] == "panel":
            panels.append(content)
        for item in content.get("items", []):
            walk(item["content"])

    walk(layout["content"])
    assert panels[0]["panelType"] == "ThreeDee"  # the first, largest item
    assert {p["panelType"] for p in panels} == {"ThreeDee", "Plot", "Log"}
    served = {spec.topic for spec in standard_channels()}
    assert set(panels[0]["config"]["topics"]) <= served
    assert SCENE_TOPIC in panels[0]["config"]["topics"]
    timing = set(timing_figures({k: {"p99_us": 1.0} for k in ("compute", "latency", "jitter")}))
    for panel in panels:
        for series in panel["config"].get("paths", []):
            topic, _, field = series["value"].partition(".")
            assert topic == SERIES_TOPIC
            name = field.split("[")[0].split(".")[0]
            assert name in SERIES_SCHEMA["properties"], series
            if name == "timing":
                assert field.split(".")[1] in timing, series
    (log,) = [p for p in panels if p["panelType"] == "Log"]
    assert log["config"]["topicToRender"] == LOG_TOPIC
