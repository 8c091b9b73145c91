"""The robot in Foxglove's standard schemas (DESIGN §17): one implementation for the live
view (daemon.process.live_view) and the telemetry recording (recording.TelemetryRecorder),
so that a recording opened in Foxglove shows the scene the live view showed.

From a cycle record (daemon.process.recording.CycleRecord) the SceneBuilder makes, all
in the world frame (z up, m):

    /tf                   foxglove.FrameTransforms  world -> platform, world -> reference
    /cdpr/scene           foxglove.SceneUpdate      the frame (anchors' bounding box) and
                          anchors, the workspace box, each cable as a line from its anchor
                          to its attachment point coloured by tension (tension_color;
                          slack cables grey and labelled, faulted ones magenta and
                          labelled), the platform as the box round its body
                          (platform_box), the reference pose as a ghost of it
    /cdpr/pose            foxglove.PoseInFrame      measured platform pose
    /cdpr/reference_pose  foxglove.PoseInFrame      reference pose (while there is one)
    /cdpr/series          JSON, cdprd.Series        tensions, forces, lengths, tracking
                                                    error, safety state, cycle timing
    /cdpr/workspace       foxglove.SceneUpdate      the saved workspace map's boundary at
                          home coloured by margin, the environment's boxes, the box
                          (workspace_scene; now and then, for clients that join late)

and from a core event (state changes, brakes, trajectories) a foxglove.Log on /cdpr/log.
Messages leave here encoded (protobuf, JSON), as (topic, bytes).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from foxglove.messages import (
    Color,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Pose,
    PoseInFrame,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from cdpr import Pose as CdprPose
from cdpr import Robot, liediff
from cdpr.body import Environment, Plane
from daemon.interface.robot_drawing import (
    ANCHOR_COLOR,
    PLATFORM_COLOR,
    attachments_at,
    cable_styles,
    platform_box,
    tension_color,
)
from daemon.process.recording import ChannelSpec, CycleRecord, json_bytes

WORLD, PLATFORM, REFERENCE = "world", "platform", "reference"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/cdpr/scene"
POSE_TOPIC = "/cdpr/pose"
REFERENCE_POSE_TOPIC = "/cdpr/reference_pose"
SERIES_TOPIC = "/cdpr/series"
LOG_TOPIC = "/cdpr/log"
WORKSPACE_TOPIC = "/cdpr/workspace"
SERIES_SCHEMA_NAME = "cdprd.Series"

_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}
SERIES_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": SERIES_SCHEMA_NAME,
    "description": "cdprd's numeric series for plots, SI units, cable order",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "cycle time, daemon clock (s)"},
        "tensions": {**_NUMBERS, "description": "cable tensions (N)"},
        "forces": {**_NUMBERS, "description": "commanded actuator forces (N)"},
        "lengths": {**_NUMBERS, "description": "measured cable lengths (m)"},
        "tracking_error": {
            "type": ["object", "null"],
            "description": "measured - reference: |position| (m), rotation angle (rad)",
            "properties": {"position": {"type": "number"}, "orientation": {"type": "number"}},
        },
        "safety": {"type": "string"},
        "timing": {
            "type": "object",
            "description": "the core's cycle figures (µs where the name ends in _us)",
            "additionalProperties": {"type": "number"},
        },
    },
}


def standard_channels() -> tuple[ChannelSpec, ...]:
    """The channels of the scene: topic, encoding and schema, for a server or an MCAP."""
    typed = (
        (TF_TOPIC, FrameTransforms),
        (SCENE_TOPIC, SceneUpdate),
        (POSE_TOPIC, PoseInFrame),
        (REFERENCE_POSE_TOPIC, PoseInFrame),
        (LOG_TOPIC, Log),
        (WORKSPACE_TOPIC, SceneUpdate),
    )
    specs = []
    for topic, message in typed:
        schema = message.get_schema()
        specs.append(ChannelSpec(topic, "protobuf", schema.name, schema.encoding, schema.data))
    series = json_bytes(SERIES_SCHEMA)
    specs.append(ChannelSpec(SERIES_TOPIC, "json", SERIES_SCHEMA_NAME, "jsonschema", series))
    return tuple(specs)


def timing_figures(cycle: Mapping[str, Any] | None) -> dict[str, float]:
    """A state snapshot's "cycle" figures, flat: {"compute_p99_us": .., "cycles": ..}."""
    flat: dict[str, float] = {}
    for key, value in (cycle or {}).items():
        if isinstance(value, Mapping):
            for sub, number in value.items():
                if isinstance(number, int | float):
                    flat[f"{key}_{sub}"] = float(number)
        elif isinstance(value, int | float) and not isinstance(value, bool):
            flat[key] = float(value)
    return flat


class SceneBuilder:
    """Foxglove messages of `robot` in the workspace box `workspace` (lo, hi corners)."""

    def __init__(self, robot: Robot, workspace: tuple[Sequence[float], Sequence[float]]) -> None:
        self.robot = robot
        self.anchors = robot.geometry.anchors
        self.attachments = robot.geometry.attachments
        self.box_center, self.box_size = platform_box(robot)  # platform frame
        self.workspace = (np.asarray(workspace[0], float), np.asarray(workspace[1], float))

    # -- encoded, for the sinks -----------------------------------------------------------

    def encode(
        self,
        record: CycleRecord,
        stamp_ns: int,
        faults: Sequence[str | None] = (),
        timing: Mapping[str, float] | None = None,
    ) -> list[tuple[str, bytes]]:
        """Every message of one cycle, encoded, as (topic, data)."""
        out = [
            (TF_TOPIC, self.transforms(record, stamp_ns).encode()),
            (SCENE_TOPIC, self.scene(record, stamp_ns, faults).encode()),
            (POSE_TOPIC, _pose_in_frame(record.position, record.quaternion, stamp_ns).encode()),
        ]
        if record.reference is not None:
            reference = _pose_in_frame(*record.reference, stamp_ns)
            out.append((REFERENCE_POSE_TOPIC, reference.encode()))
        out.append((SERIES_TOPIC, json_bytes(self.series(record, timing))))
        return out

    def encode_event(self, event: Mapping[str, Any], stamp_ns: int) -> list[tuple[str, bytes]]:
        """A core event as a foxglove.Log on LOG_TOPIC."""
        level, text = _event_text(event)
        log = Log(timestamp=_stamp(stamp_ns), level=level, message=text, name="cdprd")
        return [(LOG_TOPIC, log.encode())]

    # -- the messages ---------------------------------------------------------------------

    def transforms(self, record: CycleRecord, stamp_ns: int) -> FrameTransforms:
        """world -> platform, and world -> reference while there is a reference."""
        frames = [(PLATFORM, record.position, record.quaternion)]
        if record.reference is not None:
            frames.append((REFERENCE, *record.reference))
        return FrameTransforms(
            transforms=[
                FrameTransform(
                    timestamp=_stamp(stamp_ns),
                    parent_frame_id=WORLD,
                    child_frame_id=child,
                    translation=_vector(p),
                    rotation=_quaternion(q),
                )
                for child, p, q in frames
            ]
        )

    def attachment_points(self, position: Sequence[float], quaternion: Sequence[float]):
        """The attachment points in the world at the pose (n x 3)."""
        return attachments_at(self.attachments, position, quaternion)

    def scene(
        self, record: CycleRecord, stamp_ns: int, faults: Sequence[str | None] = ()
    ) -> SceneUpdate:
        """The whole scene at one cycle (entities replace those of the same id)."""
        stamp = _stamp(stamp_ns)
        entities = [
            self._frame(stamp),
            self._workspace(stamp),
            self._cables(record, stamp, faults),
            self._box("platform", record.position, record.quaternion, PLATFORM_COLOR, stamp),
        ]
        deletions = []
        if record.reference is not None:
            ghost = (0.7, 0.7, 1.0, 0.3)
            entities.append(self._box("reference", *record.reference, ghost, stamp))
        else:
            deletions.append(
                SceneEntityDeletion(
                    timestamp=stamp, type=SceneEntityDeletionType.MatchingId, id="reference"
                )
            )
        return SceneUpdate(deletions=deletions, entities=entities)

    def series(
        self, record: CycleRecord, timing: Mapping[str, float] | None = None
    ) -> dict[str, Any]:
        """The numeric series of one cycle (SERIES_SCHEMA)."""
        error = None
        if record.reference is not None:
            measured = CdprPose(record.position, record.quaternion)
            theta = liediff(CdprPose(*record.reference), measured)
            error = {
                "position": float(np.linalg.norm(theta[:3])),
                "orientation": float(np.linalg.norm(theta[3:])),
            }
        return {
            "t": record.t,
            "tensions": list(record.tensions),
            "forces": list(record.forces),
            "lengths": list(record.lengths),
            "tracking_error": error,
            "safety": record.safety,
            "timing": dict(timing or {}),
        }

    # -- entities -------------------------------------------------------------------------

    def _frame(self, stamp: Timestamp) -> SceneEntity:
        lo, hi = self.anchors.min(axis=0), self.anchors.max(axis=0)
        return SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id="frame",
            lines=[_box_lines(lo, hi, (0.3, 0.3, 0.3, 1.0))],
            spheres=[
                SpherePrimitive(
                    pose=Pose(position=_vector(a), orientation=Quaternion(w=1.0)),
                    size=Vector3(x=0.04, y=0.04, z=0.04),
                    color=_color(ANCHOR_COLOR),
                )
                for a in self.anchors
            ],
        )

    def _workspace(self, stamp: Timestamp) -> SceneEntity:
        lo, hi = self.workspace
        return SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id="workspace",
            cubes=[
                CubePrimitive(
                    pose=Pose(position=_vector((lo + hi) / 2.0), orientation=Quaternion(w=1.0)),
                    size=_vector(hi - lo),
                    color=_color((0.2, 0.8, 0.3, 0.06)),
                )
            ],
            lines=[_box_lines(lo, hi, (0.2, 0.6, 0.3, 0.5))],
        )

    def _cables(
        self, record: CycleRecord, stamp: Timestamp, faults: Sequence[str | None]
    ) -> SceneEntity:
        ends = self.attachment_points(record.position, record.quaternion)
        styles = cable_styles(self.robot, record.tensions, faults)
        lines, texts = [], []
        for a, b, (color, width, label) in zip(self.anchors, ends, styles, strict=True):
            lines.append(
                LinePrimitive(
                    type=LinePrimitiveLineType.LineStrip,
                    thickness=width,
                    points=[_point(a), _point(b)],
                    color=_color(color),
                )
            )
            if label is not None:
                texts.append(
                    TextPrimitive(
                        pose=Pose(position=_vector((a + b) / 2.0), orientation=Quaternion(w=1.0)),
                        billboard=True,
                        font_size=14.0,
                        scale_invariant=True,
                        color=_color((*color[:3], 1.0)),
                        text=label,
                    )
                )
        return SceneEntity(timestamp=stamp, frame_id=WORLD, id="cables", lines=lines, texts=texts)

    def _box(
        self,
        ident: str,
        position: Sequence[float],
        quaternion: Sequence[float],
        color: tuple[float, float, float, float],
        stamp: Timestamp,
    ) -> SceneEntity:
        """The platform's box (through its attachment points) at a pose."""
        pose = CdprPose(position, quaternion)
        center = pose.position + pose.rotation @ self.box_center
        return SceneEntity(
            timestamp=stamp,
            frame_id=WORLD,
            id=ident,
            cubes=[
                CubePrimitive(
                    pose=Pose(position=_vector(center), orientation=_quaternion(quaternion)),
                    size=_vector(self.box_size),
                    color=_color(color),
                )
            ],
        )


def _box_lines(lo: np.ndarray, hi: np.ndarray, color: tuple) -> LinePrimitive:
    """The 12 edges of the axis-aligned box lo..hi as one line list."""
    corners = [np.where([i & 1, i & 2, i & 4], hi, lo) for i in range(8)]
    edges = [(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit]
    return LinePrimitive(
        type=LinePrimitiveLineType.LineList,
        thickness=2.0,
        scale_invariant=True,
        points=[_point(corners[k]) for edge in edges for k in edge],
        color=_color(color),
    )


def _event_text(event: Mapping[str, Any]) -> tuple[LogLevel, str]:
    kind = event.get("event", "event")
    state = event.get("state")
    if kind == "brake":
        return LogLevel.Error, f"brake: {event.get('trigger')}: {event.get('message')}"
    if kind == "trajectory_rejected":
        error = event.get("error") or {}
        reason = error.get("reason", error) if isinstance(error, Mapping) else error
        return LogLevel.Warning, f"trajectory {event.get('id')} rejected: {reason}"
    if kind == "state":
        return LogLevel.Info, f"{state}: {event.get('why', '')}".rstrip(": ")
    detail = ", ".join(f"{k}={v}" for k, v in event.items() if k not in ("event", "t"))
    return LogLevel.Info, f"{kind}: {detail}" if detail else str(kind)


def _stamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


PLANE_THICKNESS = 0.002  # m: a plane drawn as a square this thin


def _plane_square(plane: Plane, corners: tuple[Sequence[float], Sequence[float]]) -> CubePrimitive:
    """A plane as a thin translucent square on it, as wide as the box `corners`'
    diagonal, centred where the box's centre projects onto it."""
    lo, hi = (np.asarray(c, dtype=float) for c in corners)
    normal = np.asarray(plane.normal, dtype=float)
    centre = (lo + hi) / 2.0
    on_plane = centre - (centre.dot(normal) - plane.offset) * normal
    width = float(np.linalg.norm(hi - lo))
    # the rotation taking z onto the normal: about z x n by the angle between them
    axis = np.cross((0.0, 0.0, 1.0), normal)
    sine, cosine = float(np.linalg.norm(axis)), float(normal[2])
    if sine < 1e-12:  # along z already (or against it: a half turn about x)
        turn = Quaternion(w=1.0) if cosine > 0 else Quaternion(x=1.0, w=0.0)
    else:
        half = np.arctan2(sine, cosine) / 2.0
        x, y, z = axis / sine * np.sin(half)
        turn = Quaternion(x=float(x), y=float(y), z=float(z), w=float(np.cos(half)))
    return CubePrimitive(
        pose=Pose(position=_vector(on_plane), orientation=turn),
        size=Vector3(x=width, y=width, z=PLANE_THICKNESS),
        color=_color((0.45, 0.45, 0.5, 0.25)),
    )


def _vector(v: Sequence[float]) -> Vector3:
    x, y, z = (float(c) for c in v)
    return Vector3(x=x, y=y, z=z)


def _point(v: Sequence[float]) -> Point3:
    x, y, z = (float(c) for c in v)
    return Point3(x=x, y=y, z=z)


def _quaternion(q: Sequence[float]) -> Quaternion:
    """(w, x, y, z), the project's order, as Foxglove's quaternion."""
    w, x, y, z = (float(c) for c in q)
    return Quaternion(x=x, y=y, z=z, w=w)


def _color(c: Sequence[float]) -> Color:
    r, g, b, a = (float(v) for v in c)
    return Color(r=r, g=g, b=b, a=a)


def _pose_in_frame(
    position: Sequence[float], quaternion: Sequence[float], stamp_ns: int
) -> PoseInFrame:
    return PoseInFrame(
        timestamp=_stamp(stamp_ns),
        frame_id=WORLD,
        pose=Pose(position=_vector(position), orientation=_quaternion(quaternion)),
    )


def workspace_scene(
    corners: tuple[Sequence[float], Sequence[float]],
    voxels: np.ndarray,
    margins: np.ndarray,
    size: float,
    environment: Environment,
    anchors: np.ndarray,
    stamp_ns: int = 0,
) -> SceneUpdate:
    """The workspace in the world frame: the box `corners` (lo, hi) as lines, each voxel
    centre of `voxels` (N x 3, m) a cube of side `size` coloured by its margin (N:
    tension_color of margin / the largest), the environment's boxes as translucent grey
    cubes and its planes (floor, walls) as thin translucent squares across the box, and
    the frame's `anchors` (n x 3) as spheres."""
    stamp = _stamp(stamp_ns)
    top = float(margins.max()) if len(margins) else 1.0
    cubes = [
        CubePrimitive(
            pose=Pose(position=_vector(v), orientation=Quaternion(w=1.0)),
            size=Vector3(x=size, y=size, z=size),
            color=_color(tension_color(float(m) / top)),
        )
        for v, m in zip(voxels.tolist(), margins.tolist(), strict=True)
    ]
    obstacles = [
        CubePrimitive(
            pose=Pose(
                position=_vector((np.asarray(box.lower) + np.asarray(box.upper)) / 2.0),
                orientation=Quaternion(w=1.0),
            ),
            size=_vector(np.asarray(box.upper) - np.asarray(box.lower)),
            color=_color((0.5, 0.5, 0.5, 0.4)),
        )
        for box in environment.boxes
    ]
    obstacles += [_plane_square(plane, corners) for plane in environment.planes]
    lo, hi = (np.asarray(c, dtype=float) for c in corners)
    return SceneUpdate(
        entities=[
            SceneEntity(timestamp=stamp, frame_id=WORLD, id="workspace", cubes=cubes),
            SceneEntity(
                timestamp=stamp,
                frame_id=WORLD,
                id="environment",
                cubes=obstacles,
                lines=[_box_lines(lo, hi, (0.6, 0.6, 0.6, 1.0))],
                spheres=[
                    SpherePrimitive(
                        pose=Pose(position=_vector(a), orientation=Quaternion(w=1.0)),
                        size=Vector3(x=0.05, y=0.05, z=0.05),
                        color=_color((0.3, 0.3, 0.3, 1.0)),
                    )
                    for a in np.asarray(anchors, dtype=float).tolist()
                ],
            ),
        ]
    )
