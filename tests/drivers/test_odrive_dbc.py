"""Our ODrive frames and DBC against ODrive's own DBC for firmware 0.6.10 (tests/data).

The reference was written by ODrive, not by this project: every frame the host driver and
the simulated ODrive put on the bus in a loopback run must decode strictly with it, with
the message's length, and our shipped DBC must lay every message out as it does.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import can
import cantools
from cantools.database.namedsignalvalue import NamedSignalValue

from drivers.base import BrakeMode
from drivers.odrive import codec
from drivers.odrive.codec import Cmd
from tests.drivers.test_odrive_device import HOLDING, NODES, enabled, started

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "tests" / "data" / "odrive-cansimple-0.6.10.dbc"
SHIPPED = ROOT / "config" / "can" / "odrive_cansimple.dbc"


def load(path: Path) -> cantools.database.can.Database:
    return cantools.database.load_file(path, strict=True)


def layout(message: cantools.database.can.Message) -> dict[str, tuple]:
    return {
        s.name: (
            s.start,
            s.length,
            s.byte_order,
            s.is_signed,
            s.is_float,
            s.scale,
            s.offset,
            {int(k): str(v) for k, v in (s.choices or {}).items()},
        )
        for s in message.signals
    }


def test_shipped_dbc_lays_out_every_message_as_odrives() -> None:
    ours, reference = load(SHIPPED), load(REFERENCE)
    assert {m.frame_id for m in ours.messages} == {int(cmd) for cmd in Cmd}
    for message in ours.messages:
        theirs = reference.get_message_by_frame_id(message.frame_id)  # node 0: Axis0_
        assert theirs.name == "Axis0_" + message.name
        assert message.length == theirs.length == codec.LENGTHS[Cmd(message.frame_id)]
        assert layout(message) == layout(theirs), message.name


def loopback_frames() -> tuple[list[can.Message], list[can.Message]]:
    """(host frames, device frames) of start, enable, commands, both brakes, keepalive,
    an Estop and its reset, error requests and disable, on the simulated bus."""
    driver, _, link = enabled(has_holding_brake=True)
    link.run(0.05, lambda: link.send_all(driver.commands(HOLDING)))
    lengths = [f.length for f in driver.feedback]
    link.send_all(driver.brake(lengths, BrakeMode.POSITION_HOLD))
    link.run(0.05, lambda: link.send_all(driver.keepalive()))
    link.send_all(driver.brake(lengths, BrakeMode.HOLDING_BRAKE))
    link.run(0.05, lambda: link.send_all(driver.keepalive()))
    link.send(codec.encode_estop(NODES[1]))
    link.send_all(driver.request_errors())
    link.run(0.15, lambda: link.send_all(driver.keepalive()))
    asyncio.run(driver.reset_faults(link))
    asyncio.run(driver.enable(link, [f.length for f in driver.feedback], HOLDING))
    link.send_all(driver.disable())
    link.run(0.05, lambda: link.send_all(driver.keepalive()))
    host, device = link.sent, link.heard
    unbraked, _, link = started()  # the other start: position hold without brakes
    link.run(0.05, lambda: link.send_all(unbraked.keepalive()))
    return host + link.sent, device + link.heard


def test_every_frame_on_the_loopback_bus_decodes_strictly_with_odrives_dbc() -> None:
    reference = load(REFERENCE)
    host, device = loopback_frames()
    seen: dict[str, set[str]] = {"host": set(), "device": set()}
    for side, frames in (("host", host), ("device", device)):
        for frame in frames:
            assert not frame.is_extended_id and frame.arbitration_id >> 5 in NODES
            spec = reference.get_message_by_frame_id(frame.arbitration_id & codec.CMD_MASK)
            if frame.is_remote_frame:
                assert frame.dlc == spec.length, spec.name
                seen[side].add(spec.name + " (RTR)")
                continue
            assert len(frame.data) == spec.length, (spec.name, bytes(frame.data))
            values = spec.decode(
                bytes(frame.data), decode_choices=True, allow_truncated=False, allow_excess=False
            )
            for name in ("Axis_State", "Axis_Requested_State", "Control_Mode", "Input_Mode"):
                if name in values:  # a value the reference's table names
                    assert isinstance(values[name], NamedSignalValue), (name, values[name])
            seen[side].add(spec.name)
    assert seen["host"] == {
        "Axis0_Estop",
        "Axis0_Set_Axis_State",
        "Axis0_Set_Controller_Mode",
        "Axis0_Set_Input_Pos",
        "Axis0_Set_Input_Torque",
        "Axis0_Clear_Errors",
        "Axis0_Heartbeat (RTR)",
        "Axis0_Get_Encoder_Estimates (RTR)",
        "Axis0_Get_Error (RTR)",
    }
    assert seen["device"] == {"Axis0_Heartbeat", "Axis0_Get_Encoder_Estimates", "Axis0_Get_Error"}
