"""The simulator hands a frame only to the drives that hear its id (VirtualRobot's route
table), and a drive whose ids change (an SDO moves its SYNC, a PDO's COB-ID) hears the new
ones at once: the table is rebuilt when a drive says its routes changed."""

from __future__ import annotations

import struct

import can

from drivers.cia402.codec import (
    COB_ID_SYNC,
    SYNC_ID,
    NmtCommand,
    encode_nmt,
    encode_sdo_download_request,
    encode_sync,
)
from sim_bus.virtual_robot import VirtualRobot
from tests.daemon_stack import config_for

SDO_RESPONSE_BASE = 0x580


def operational_robot() -> VirtualRobot:
    """The cia402 example's simulated robot, booted, every node OPERATIONAL."""
    config = config_for("cia402")
    robot = VirtualRobot(config.robot, config.drives)
    robot.advance_to(0.01)
    robot.handle(encode_nmt(NmtCommand.START, 0), robot.t)
    return robot


def taking(robot: VirtualRobot, frame: can.Message) -> set[int]:
    """The nodes that accepted `frame` (their FrameCounters)."""
    before = [d.counters.accepted for d in robot.drives]
    robot.handle(frame, robot.t)
    return {d.node_id for d, n in zip(robot.drives, before, strict=True) if d.counters.accepted > n}


def sync_on(can_id: int) -> can.Message:
    return can.Message(arbitration_id=can_id, data=encode_sync().data, is_extended_id=False)


def test_a_moved_sync_is_heard_on_its_new_id_and_no_longer_on_the_old() -> None:
    robot = operational_robot()
    nodes = {d.node_id for d in robot.drives}
    assert taking(robot, sync_on(SYNC_ID)) == nodes
    moved = SYNC_ID + 1
    assert taking(robot, sync_on(moved)) == set()  # nobody hears it: now in the table
    node = robot.drives[0].node_id
    write = encode_sdo_download_request(node, COB_ID_SYNC, 0, struct.pack("<I", moved))
    (reply,) = robot.handle(write, robot.t)
    assert reply.arbitration_id == SDO_RESPONSE_BASE + node and reply.data[0] == 0x60
    assert taking(robot, sync_on(moved)) == {node}
    assert taking(robot, sync_on(SYNC_ID)) == nodes - {node}


def test_frames_on_ids_no_drive_has_reach_none_of_them() -> None:
    robot = operational_robot()
    heard = [0] * robot.n
    for k, drive in enumerate(robot.drives):

        def counting(message: can.Message, now: float, k: int = k, inner=drive.on_frame) -> list:
            heard[k] += 1
            return inner(message, now)

        drive.on_frame = counting  # type: ignore[method-assign]
    for can_id in (0x7E5, 0x123, 0x6FF):  # LSS, nobody's PDO, node 127's SDO request
        robot.handle(can.Message(arbitration_id=can_id, data=b"\0" * 8, is_extended_id=False), 0.02)
    assert heard == [0] * robot.n
    robot.handle(sync_on(SYNC_ID), robot.t)
    assert heard == [1] * robot.n
