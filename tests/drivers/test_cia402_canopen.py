"""Conformance against code the project did not write: the `canopen`
package plays the drives for our host, and the master for our simulated drive.

Slaves: tests/canopen_drive.py (canopen's LocalNode with a vendor-style EDS and its
default mapping).  Our host
(Cia402Driver through the daemon's BusPort) brings three of them up on a python-can
virtual bus in this process: it maps their PDOs by SDO, and they enable, hold and take
torque as canopen decodes our frames; a restarted host takes them over under torque
(no NMT pre-operational, no torque step).

Master: canopen's RemoteNode configures our simulated drive (sim_bus process over
socketcand) with its own PDO API and drives it through the 402 machine."""

from __future__ import annotations

import asyncio
import itertools
import time
from pathlib import Path

import can
import canopen
import pytest

from cdpr.description import load_yaml
from daemon.service.bus_port import BusPort
from drivers.base import DriveState
from drivers.cia402.codec import EDS_PATH
from drivers.cia402.host import Cia402Driver
from drivers.config import parse_drives
from tests.canopen_drive import ENABLED, SWITCHED_ON, VENDOR_EDS, CanopenDrive
from tests.processes import serve_simulator

ROOT = Path(__file__).resolve().parents[2]
TWO_BUS = ROOT / "config" / "reference8-cia402-2bus.yaml"
NODES = [1, 2, 3]
RADIUS = 0.05
CHANNELS = itertools.count()

pytestmark = pytest.mark.timeout(60)


def host_config(eds: Path = VENDOR_EDS, **profile: object):
    return parse_drives(
        {
            "protocol": "cia402",
            "nodes": NODES,
            "rated_torque": 1.0,  # 0x6076 = 1000 mN·m in the vendor EDS
            "gear_ratio": 10.0,
            "counts_per_rev": 4096,
            "watchdog_timeout": 0.2,
            "heartbeat_timeout": 1.0,
            "consumer_heartbeat_time": 1.0,
            "profile": {"eds": str(eds), **profile},
        }
    )


async def until(condition, what: str, polls: int = 400) -> None:
    for _ in range(polls):
        if condition():
            return
        await asyncio.sleep(0.005)
    raise AssertionError(f"not within {polls} polls: {what}")


def test_our_host_brings_up_canopen_slaves_with_their_vendor_default_mapping() -> None:
    channel = f"cdprd-canopen-{next(CHANNELS)}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    config = host_config()
    scalings = config.scalings([RADIUS] * len(NODES))
    length = 1.5
    drives = [
        CanopenDrive(network, node, round(s.position(length)))
        for node, s in zip(NODES, scalings, strict=True)
    ]
    # the vendor's defaults: RPDO1 = controlword, TPDO1 = statusword, event-driven
    assert [drives[0].value(0x1600, k) for k in (0, 1)] == [1, 0x60400010]
    assert [drives[0].value(0x1A00, k) for k in (0, 1)] == [1, 0x60410010]
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    restarted = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    driver = Cia402Driver(config, scalings)
    driver.sdo_timeout = 2.0  # a loaded machine: canopen answers from its own thread

    async def scenario() -> None:
        port = BusPort(bus, lambda frames, now: [driver.receive(f, now) for f in frames])
        port.open(asyncio.get_running_loop())
        try:
            await driver.start(port, time.monotonic)
            for drive in drives:  # canopen's own reading of what our host configured
                node = drive.node
                assert node.nmt.state == "OPERATIONAL"
                assert drive.value(0x6041) == SWITCHED_ON
                tpdo1, rpdo1 = node.tpdo[1], node.rpdo[1]
                assert [v.index for v in tpdo1.map] == [0x6041, 0x6064, 0x6061]
                assert tpdo1.trans_type == 1 and tpdo1.enabled
                assert [v.index for v in rpdo1.map] == [0x6040, 0x6071, 0x6060]
                assert [v.index for v in node.rpdo[2].map] == [0x6040, 0x607A, 0x6060]
                assert drive.value(0x1016, 1) == 127 << 16 | 1000  # our heartbeat, 1 s
                assert (drive.value(0x6007), drive.value(0x605A)) == (3, 6)
                assert drive.value(0x1017) == 100
            await driver.enable(port, [length] * len(NODES), [0.0] * len(NODES))
            for drive in drives:  # holding where they are, in cyclic synchronous position
                assert drive.value(0x6041) == ENABLED and drive.value(0x6061) == 8
                assert drive.value(0x607A) == drive.value(0x6064)
            for _ in range(5):
                for frame in driver.cycle_start() + driver.commands([10.0, -20.0, 30.0]):
                    port.send(frame)
                await asyncio.sleep(0.01)
            await until(lambda: all(len(d.torques) >= 5 for d in drives), "torque commands")
            # per mille of the rated torque 1 N·m: 10 N on a 5 cm drum, 10:1 -> 50
            assert [d.torques[-1] for d in drives] == [50, -100, 150]
            assert all(d.value(0x6061) == 10 for d in drives)
            # feedback: TPDO1 + TPDO2 on SYNC, decoded by our host
            counts = [fb.count for fb in driver.feedback]
            port.send(driver.cycle_start()[0])
            await until(
                lambda: all(fb.count > c for fb, c in zip(driver.feedback, counts, strict=True)),
                "feedback after SYNC",
            )
            assert all(fb.length == pytest.approx(length, abs=1e-3) for fb in driver.feedback)
        finally:
            port.close()
        # the daemon restarts: a new host finds them enabled under torque and takes them
        # over without a torque step and without NMT pre-operational
        nmt: list[bytes] = []
        network.subscribe(0x000, lambda can_id, data, t: nmt.append(bytes(data)))
        marks = [len(d.torques) for d in drives]
        again = Cia402Driver(config, scalings)
        again.sdo_timeout = 2.0
        port = BusPort(restarted, lambda frames, now: [again.receive(f, now) for f in frames])
        port.open(asyncio.get_running_loop())
        try:
            await again.start(port, time.monotonic)
        finally:
            port.close()
        assert {data[0] for data in nmt} == {0x01}  # NMT start only
        assert all(d.value(0x6041) == ENABLED and d.value(0x6061) == 10 for d in drives)
        held = [set(d.torques[m:]) for d, m in zip(drives, marks, strict=True)]
        assert held == [{50}, {-100}, {150}]

    try:
        asyncio.run(asyncio.wait_for(scenario(), 45))
    finally:
        bus.shutdown()
        restarted.shutdown()
        network.disconnect()


def test_canopen_slaves_take_the_compact_layout_with_one_torque_frame_for_all() -> None:
    """The layout of config/reference8-cia402-2bus.yaml: canopen reads the shared RPDO's
    dummy entries from the mapping our host wrote, and each slave takes its own torque
    from the one frame; the statusword comes on change, the position on SYNC."""
    channel = f"cdprd-canopen-{next(CHANNELS)}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    compact = load_yaml(TWO_BUS)["drives"]["profile"]
    config = host_config(rpdo=compact["rpdo"], tpdo=compact["tpdo"])
    scalings = config.scalings([RADIUS] * len(NODES))
    length = 1.5
    drives = [
        CanopenDrive(network, node, round(s.position(length)))
        for node, s in zip(NODES, scalings, strict=True)
    ]
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    driver = Cia402Driver(config, scalings)
    driver.sdo_timeout = 2.0

    async def scenario() -> None:
        port = BusPort(bus, lambda frames, now: [driver.receive(f, now) for f in frames])
        port.open(asyncio.get_running_loop())
        try:
            await driver.start(port, time.monotonic)
            for slot, drive in enumerate(drives):  # canopen's own reading of the mapping
                rpdo1 = drive.node.rpdo[1]
                assert rpdo1.cob_id == 0x201 and rpdo1.enabled
                assert [v.index for v in rpdo1.map] == [
                    0x6071 if k == slot else 0x0006 for k in range(len(NODES))
                ]
                assert [v.index for v in drive.node.rpdo[3].map] == [0x6040, 0x6060]
                assert [v.index for v in drive.node.tpdo[1].map] == [0x6064]
                tpdo2 = drive.node.tpdo[2]
                assert [v.index for v in tpdo2.map] == [0x6041, 0x6061]
                assert tpdo2.trans_type == 255 and drive.value(0x1801, 3) == 10
            await driver.enable(port, [length] * len(NODES), [0.0] * len(NODES))
            assert all(d.value(0x6041) == ENABLED and d.value(0x6061) == 8 for d in drives)
            sent: list[can.Message] = []
            for _ in range(6):  # the first torque finds mode 8: the mode follows it
                for frame in driver.cycle_start() + driver.commands([10.0, -20.0, 30.0]):
                    sent.append(frame)
                    port.send(frame)
                await asyncio.sleep(0.01)
            await until(lambda: all(len(d.torques) >= 5 for d in drives), "torque commands")
            assert [d.torques[-1] for d in drives] == [50, -100, 150]
            assert all(d.value(0x6061) == 10 for d in drives)
            torque_frames = [m for m in sent if m.arbitration_id == 0x201]
            assert len(torque_frames) == 6 and all(len(m.data) == 6 for m in torque_frames)
            assert len([m for m in sent if 0x401 <= m.arbitration_id <= 0x403]) == 3  # once
            counts = [fb.count for fb in driver.feedback]
            port.send(driver.cycle_start()[0])
            await until(
                lambda: all(fb.count > c for fb, c in zip(driver.feedback, counts, strict=True)),
                "feedback after SYNC",
            )
            assert all(fb.length == pytest.approx(length, abs=1e-3) for fb in driver.feedback)
            assert all(s.state is DriveState.ENABLED for s in driver.status)
        finally:
            port.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 45))
    finally:
        bus.shutdown()
        network.disconnect()


def test_canopen_as_master_configures_and_drives_our_simulated_drive() -> None:
    """canopen's RemoteNode (SDO client, PDO API, NMT, SYNC) and our strict simulated
    drive (the sim_bus process over socketcand) with the drive's own EDS."""
    proc, port, channel = serve_simulator(ROOT / "config" / "reference8-cia402.yaml")
    network = canopen.Network()
    try:
        network.connect(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
        node = network.add_node(1, str(EDS_PATH))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        assert node.sdo[0x1000].raw & 0xFFFF == 402
        assert node.sdo[0x1008].raw == "cdprd CiA 402 CST winch drive"  # segmented upload
        with pytest.raises(canopen.SdoAbortedError) as aborted:
            node.sdo[0x6041].raw = 0  # read-only
        assert aborted.value.code == 0x06010002
        node.tpdo.read()
        node.rpdo.read()
        assert [v.index for v in node.tpdo[1].map] == [0x6041]  # the vendor default
        assert [v.index for v in node.rpdo[1].map] == [0x6040]
        # canopen's own CiA 301 procedure (our drive refuses any other)
        tpdo, rpdo = node.tpdo[1], node.rpdo[1]
        tpdo.clear()
        for index in (0x6041, 0x6064, 0x6061):
            tpdo.add_variable(index)
        tpdo.trans_type, tpdo.enabled = 1, True
        rpdo.clear()
        for index in (0x6040, 0x6060, 0x607A):
            rpdo.add_variable(index)
        rpdo.trans_type, rpdo.enabled = 255, True
        node.tpdo.save()
        node.rpdo.save()
        assert node.sdo[0x1A00][0].raw == 3 and node.sdo[0x1600][2].raw == 0x60600008
        node.sdo[0x1017].raw = 100
        node.nmt.state = "OPERATIONAL"
        node.nmt.wait_for_heartbeat(5.0)
        assert node.nmt.state == "OPERATIONAL"
        # the 402 machine by SDO, into cyclic synchronous position at the actual position
        position = node.sdo[0x6064].raw
        node.sdo[0x6060].raw = 8
        node.sdo[0x607A].raw = position
        for controlword in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = controlword
        assert node.sdo[0x6041].raw & 0x6F == 0x27  # OPERATION ENABLED
        # feedback on SYNC, decoded by canopen
        # (the drive may answer before wait_for_reception would start: watch the stamp)
        before, end = tpdo.timestamp, time.monotonic() + 5.0
        network.sync.transmit()
        while tpdo.timestamp == before and time.monotonic() < end:
            time.sleep(0.01)
        assert tpdo.timestamp != before, "no TPDO1 after SYNC"
        assert tpdo[0x6041].raw & 0x6F == 0x27 and tpdo[0x6061].raw == 8
        assert abs(tpdo[0x6064].raw - position) < 50
        # commands by RPDO: disable operation
        rpdo[0x6040].raw, rpdo[0x6060].raw, rpdo[0x607A].raw = 0x07, 0, position
        rpdo.transmit()
        for _ in range(100):
            if node.sdo[0x6041].raw & 0x6F == 0x23:  # SWITCHED ON
                break
        assert node.sdo[0x6041].raw & 0x6F == 0x23
        assert node.sdo[0x6061].raw == 8  # mode 0 in the RPDO: no change
    finally:
        network.disconnect()
        proc.kill()
        proc.communicate()
