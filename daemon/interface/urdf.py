"""The robot file as a URDF, for RViz's RobotModel display (docs/guide/ros2.md, "RViz"):
what robot_state_publisher would publish on `robot_description` for a cable robot.

Links, all named as the tf frames the ROS 2 bridge publishes:
- the world frame (ros2.world_frame), the root;
- one `anchor<k>` per cable, a fixed joint from the world at its anchor (world frame), a
  sphere where the cable leaves the frame;
- the platform (ros2.platform_frame), a floating joint from the world (its pose comes on
  /tf), with the robot file's mass properties and, as its visual, the box round its body
  (daemon.process.scene.platform_box: the attachment points and the file's body);
- one `attachment<k>` per cable, a fixed joint from the platform at its attachment point
  (platform frame), a small sphere.

The fixed joints are the transforms the bridge sends on /tf_static (fixed_frames), so
that RViz finds a transform for every link.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable
from typing import NamedTuple

from cdpr import Robot
from daemon.config.ros2_config import Ros2Settings
from daemon.interface.robot_drawing import ANCHOR_COLOR, PLATFORM_COLOR, platform_box

ANCHOR_RADIUS = 0.02  # m: the sphere drawn at an anchor
ATTACHMENT_RADIUS = 0.01  # m: the sphere drawn at an attachment point
ATTACHMENT_COLOR = (0.2, 0.2, 0.8, 1.0)


def anchor_frame(k: int) -> str:
    return f"anchor{k}"


def attachment_frame(k: int) -> str:
    return f"attachment{k}"


class FixedFrame(NamedTuple):
    """A frame fixed in its parent: `child` at `xyz` (m) in `parent`, not rotated."""

    parent: str
    child: str
    xyz: tuple[float, float, float]


def fixed_frames(robot: Robot, settings: Ros2Settings) -> list[FixedFrame]:
    """Each cable's anchor in the world frame, then each attachment point in the
    platform frame: the URDF's fixed joints and the transforms on /tf_static."""
    world, platform = settings.world_frame, settings.platform_frame
    anchors = [
        FixedFrame(world, anchor_frame(k), _xyz(a)) for k, a in enumerate(robot.geometry.anchors)
    ]
    attachments = [
        FixedFrame(platform, attachment_frame(k), _xyz(b))
        for k, b in enumerate(robot.geometry.attachments)
    ]
    return anchors + attachments


def robot_urdf(robot: Robot, settings: Ros2Settings) -> str:
    """The URDF of `robot` (XML text) with the frame names of `settings`."""
    root = ET.Element("robot", name=robot.name)
    for name, rgba in (
        ("anchor", ANCHOR_COLOR),
        ("platform", PLATFORM_COLOR),
        ("attachment", ATTACHMENT_COLOR),
    ):
        ET.SubElement(ET.SubElement(root, "material", name=name), "color", rgba=_numbers(rgba))
    ET.SubElement(root, "link", name=settings.world_frame)
    platform = ET.SubElement(root, "link", name=settings.platform_frame)
    center, size = platform_box(robot)
    _visual(platform, _xyz(center), "box", {"size": _numbers(size)}, "platform")
    _inertial(platform, robot)
    joint = ET.SubElement(root, "joint", name=f"{settings.platform_frame}_joint", type="floating")
    ET.SubElement(joint, "parent", link=settings.world_frame)
    ET.SubElement(joint, "child", link=settings.platform_frame)
    for frame in fixed_frames(robot, settings):
        kind = "anchor" if frame.parent == settings.world_frame else "attachment"
        radius = ANCHOR_RADIUS if kind == "anchor" else ATTACHMENT_RADIUS
        link = ET.SubElement(root, "link", name=frame.child)
        _visual(link, (0.0, 0.0, 0.0), "sphere", {"radius": repr(radius)}, kind)
        joint = ET.SubElement(root, "joint", name=f"{frame.child}_joint", type="fixed")
        ET.SubElement(joint, "parent", link=frame.parent)
        ET.SubElement(joint, "child", link=frame.child)
        ET.SubElement(joint, "origin", xyz=_numbers(frame.xyz), rpy="0 0 0")
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _visual(
    link: ET.Element,
    xyz: tuple[float, float, float],
    shape: str,
    attributes: dict[str, str],
    material: str,
) -> None:
    visual = ET.SubElement(link, "visual")
    ET.SubElement(visual, "origin", xyz=_numbers(xyz), rpy="0 0 0")
    ET.SubElement(ET.SubElement(visual, "geometry"), shape, attributes)
    ET.SubElement(visual, "material", name=material)


def _inertial(link: ET.Element, robot: Robot) -> None:
    """The robot file's mass (kg), centre of mass and inertia about it (platform frame)."""
    spec = robot.spec.platform
    inertial = ET.SubElement(link, "inertial")
    ET.SubElement(inertial, "origin", xyz=_numbers(spec.center_of_mass), rpy="0 0 0")
    ET.SubElement(inertial, "mass", value=repr(float(spec.mass)))
    (ixx, ixy, ixz), (_, iyy, iyz), (_, _, izz) = spec.inertia
    values = {"ixx": ixx, "ixy": ixy, "ixz": ixz, "iyy": iyy, "iyz": iyz, "izz": izz}
    ET.SubElement(inertial, "inertia", {k: repr(float(v)) for k, v in values.items()})


def _xyz(v: Iterable[float]) -> tuple[float, float, float]:
    x, y, z = (float(c) for c in v)
    return (x, y, z)


def _numbers(values: Iterable[float]) -> str:
    """Numbers as URDF writes them: space-separated, each as Python's shortest repr."""
    return " ".join(repr(float(v)) for v in values)
