"""The brake's confirmation reaches CiA 402 drives in every NMT state
(drivers.cia402.hold_check), host against the strict simulated drive (SDO only in
PRE-OPERATIONAL and OPERATIONAL, PDOs only in OPERATIONAL, reset communication back to
the EDS's mapping), in simulated time."""

from __future__ import annotations

import pytest

from drivers.base import Actuation, BrakeMode
from drivers.cia402 import codec
from drivers.cia402.codec import NmtCommand, NmtState
from drivers.cia402.statemachine import State
from tests.drivers.test_cia402 import make_bus

LENGTHS = [1.5, 1.5, 1.5]


def enabled_in_torque(**overrides):
    """Three drives started, enabled and following a torque command."""
    driver, devices, link = make_bus(**overrides)
    link.run(driver.enable(link, LENGTHS, [0.0] * 3))
    link.cycle([-50.0] * 3)
    assert all(d.state is State.OPERATION_ENABLED and d.mode == 10 for d in devices)
    return driver, devices, link


def brake_and_cycle(driver, link, mode=BrakeMode.POSITION_HOLD, seconds: float = 0.5) -> None:
    """Brake, then run the daemon's braked cycles for `seconds`."""
    for frame in driver.brake(LENGTHS, mode):
        link.send(frame)
    braked_cycles(driver, link, seconds)


def braked_cycles(driver, link, seconds: float) -> None:
    """The daemon's cycle while braked, every ms: SYNC and the host heartbeat (which
    keeps the drives' consumer heartbeat, and so their 0x6007 reaction, quiet), the
    feedback, then keepalive."""
    for _ in range(round(seconds / 0.001)):
        link.advance(0.001)
        link.cycle()
        for frame in driver.keepalive():
            link.send(frame)
        link.deliver()


def sdo_writes(link) -> list[tuple[int, int, bytes]]:
    """(node, index, data) of every SDO download the host sent."""
    out = []
    for frame in link.sent:
        if codec.SDO_REQUEST_BASE < frame.arbitration_id <= codec.SDO_REQUEST_BASE + 127:
            sdo = codec.decode_sdo_request(frame.arbitration_id, frame.data)
            if sdo.kind is codec.SdoKind.DOWNLOAD:
                out.append((frame.arbitration_id - codec.SDO_REQUEST_BASE, sdo.index, sdo.data))
    return out


def test_an_operational_drive_is_confirmed_by_reading_it_only() -> None:
    driver, devices, link = enabled_in_torque()
    sent = len(link.sent)
    brake_and_cycle(driver, link)
    assert [s.held for s in driver.status] == [True] * 3
    assert all(d.state is State.OPERATION_ENABLED and d.mode == 8 for d in devices)
    link.sent = link.sent[sent:]
    assert sdo_writes(link) == []  # the hold RPDO did it; the SDO reads confirm it


@pytest.mark.parametrize(
    "command",
    [NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL, NmtCommand.RESET_COMMUNICATION],
)
def test_a_drive_that_processes_no_pdo_is_quick_stopped_by_sdo(command: NmtCommand) -> None:
    driver, devices, link = enabled_in_torque()
    link.send(codec.encode_nmt(command, 0))  # another node's broadcast
    assert all(d.nmt_state is not NmtState.OPERATIONAL for d in devices)
    sent = len(link.sent)
    brake_and_cycle(driver, link)
    # the hold RPDO did not reach them; the SDO quick stop did (0x605A: hold)
    assert all(d.state is State.QUICK_STOP_ACTIVE for d in devices), [d.state for d in devices]
    assert all(d.actuation is Actuation.POSITION for d in devices)
    assert [s.held for s in driver.status] == [True] * 3
    link.sent = link.sent[sent:]
    assert {(node, index) for node, index, _ in sdo_writes(link)} == {
        (node, codec.CONTROLWORD) for node in driver.nodes
    }
    nudged = [f for f in link.sent if f.arbitration_id == codec.NMT_ID]
    # a stopped drive answers no SDO: it is sent to pre-operational first, and only it
    expected = 3 if command is NmtCommand.STOP else 0
    assert len(nudged) == expected, nudged


def test_the_holding_brake_is_engaged_by_sdo_disable_operation() -> None:
    driver, devices, link = enabled_in_torque(brake="holding_brake", has_holding_brake=True)
    link.send(codec.encode_nmt(NmtCommand.STOP, 0))
    brake_and_cycle(driver, link, BrakeMode.HOLDING_BRAKE)
    assert all(d.state is State.SWITCHED_ON and d.brake_engaged for d in devices)
    assert [s.held for s in driver.status] == [True] * 3


def test_a_silent_drive_is_reported_unconfirmed_and_asked_again() -> None:
    driver, _, link = enabled_in_torque()
    link.mute.add(driver.nodes[1])
    # two reads go unanswered (the statusword, then again after pre-operational)
    brake_and_cycle(driver, link, seconds=2 * driver.hold_check_timeout + 0.1)
    held = [s.held for s in driver.status]
    assert held == [True, False, True]
    problem = driver.status[1].hold_problem
    assert problem.startswith(f"node {driver.nodes[1]}: no answer to the statusword read"), problem
    assert "also after NMT pre-operational" in problem
    link.mute.clear()  # it comes back: the next retry confirms it
    braked_cycles(driver, link, driver.hold_check.retry + driver.hold_check_timeout)  # retry
    assert [s.held for s in driver.status] == [True] * 3


def test_a_drive_reset_without_a_hold_is_reported_nothing_holds_it() -> None:
    """Reset node puts a drive without power-on hold and without brake into SWITCH ON
    DISABLED, power stage off: no SDO can hold its cable, and the report says so."""
    driver, devices, link = enabled_in_torque()
    devices[2].power_on_hold = False
    link.send(codec.encode_nmt(NmtCommand.RESET_NODE, devices[2].node_id))
    brake_and_cycle(driver, link)
    assert [s.held for s in driver.status] == [True, True, False]
    assert "nothing holds its cable" in driver.status[2].hold_problem
    assert "SWITCH_ON_DISABLED" in driver.status[2].hold_problem


def test_torque_commands_and_sequences_end_the_check() -> None:
    driver, _, link = enabled_in_torque()
    brake_and_cycle(driver, link)
    assert driver.hold_check.armed
    link.run(driver.reset_faults(link))
    assert not driver.hold_check.armed and all(s.held is None for s in driver.status)
    brake_and_cycle(driver, link)
    link.run(driver.enable(link, LENGTHS, [0.0] * 3))
    assert not driver.hold_check.armed
    brake_and_cycle(driver, link)
    driver.commands([0.0] * 3)
    assert not driver.hold_check.armed and driver.keepalive() == []
