"""The simulated CiA 402 drive against the `canopen` package as CiA 301 master, in
simulated time: expedited SDO download without size, the TPDO event
timer, synchronous acyclic TPDOs (type 0) and synchronous RPDOs (taking effect at the next
SYNC).

canopen's Network talks to one drive through `SimulatedBus`: a frame the master sends
reaches the drive at the bus's simulated `now`, and the drive's answers reach canopen before
`send` returns, so canopen's SDO client, PDO maps, NMT and SYNC producer run unchanged with
no thread and no wall clock in between."""

from __future__ import annotations

import struct
from collections.abc import Iterator

import can
import canopen
import pytest

from drivers.cia402.codec import EDS_PATH
from drivers.cia402.statemachine import State, decode_statusword
from drivers.config import parse_drives
from sim_bus.devices.cia402 import Cia402Drive

NODE = 3
RADIUS = 0.05
LENGTH = 1.5


class SimulatedBus(can.BusABC):
    """One simulated drive on a CAN bus with canopen's `network` as the master."""

    def __init__(self, drive: Cia402Drive) -> None:
        super().__init__(channel="simulated")
        self.drive = drive
        self.now = 0.0
        self.sent: list[tuple[float, can.Message]] = []  # the drive's frames, when
        self.network = canopen.Network(self)
        self.advance(0.0)  # boot-up

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._deliver(self.drive.on_frame(msg, self.now))

    def advance(self, until: float) -> None:
        """Simulated time passes in 1 ms ticks (the simulator's rate) up to `until`."""
        tick = round(self.now * 1000)
        while True:
            self._deliver(self.drive.on_tick(self.now))
            if tick >= round(until * 1000):
                return
            tick += 1
            self.now = tick / 1000

    def times(self, cob: int, since: float) -> list[float]:
        """When the drive sent COB-ID `cob`, after `since`."""
        return [t for t, m in self.sent if m.arbitration_id == cob and t > since]

    def _deliver(self, frames: list[can.Message]) -> None:
        for frame in frames:
            self.sent.append((self.now, frame))
            self.network.notify(frame.arbitration_id, frame.data, self.now)

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        return None, False  # frames reach canopen through Network.notify


@pytest.fixture
def bus() -> Iterator[SimulatedBus]:
    config = parse_drives(
        {
            "protocol": "cia402",
            "nodes": [NODE],
            "rated_torque": 1.0,
            "gear_ratio": 10.0,
            "counts_per_rev": 4096,
        }
    )
    drive = Cia402Drive(NODE, config.scalings([RADIUS])[0], config, power_on_hold=False)
    drive.measure(LENGTH, 0.0)
    with SimulatedBus(drive) as simulated:
        yield simulated


def master(bus: SimulatedBus) -> canopen.RemoteNode:
    node = bus.network.add_node(NODE, str(EDS_PATH))
    node.tpdo.read()
    node.rpdo.read()
    return node


def state(node: canopen.RemoteNode) -> State | None:
    return decode_statusword(node.sdo[0x6041].raw)


def test_an_expedited_download_without_size_takes_the_objects_own_size(
    bus: SimulatedBus,
) -> None:
    """CiA 301 SDO download initiate, e=1 s=0: the 4 data bytes carry the object and the
    server takes its size from the dictionary (canopen's client always indicates the size:
    the frame goes raw through its SDO channel)."""
    node = master(bus)

    def unsized(index: int, sub: int, data: bytes) -> bytes:
        return node.sdo.request_response(struct.pack("<BHB4s", 0x22, index, sub, data))

    assert unsized(0x1017, 0, struct.pack("<L", 100))[0] == 0x60  # UNSIGNED16
    assert node.sdo[0x1017].raw == 100
    assert unsized(0x6060, 0, struct.pack("<L", 8))[0] == 0x60  # INTEGER8
    assert node.sdo[0x6060].raw == 8
    assert unsized(0x607A, 0, struct.pack("<l", -123456))[0] == 0x60  # INTEGER32
    assert node.sdo[0x607A].raw == -123456
    # as strict as before where the client does indicate a size
    with pytest.raises(canopen.SdoAbortedError) as aborted:
        node.sdo.request_response(struct.pack("<BHB4s", 0x2B, 0x607A, 0, bytes(4)))
    assert aborted.value.code == 0x06070010  # 2 bytes for an INTEGER32
    with pytest.raises(canopen.SdoAbortedError) as aborted:
        unsized(0x6041, 0, bytes(4))
    assert aborted.value.code == 0x06010002  # read-only
    with pytest.raises(canopen.SdoAbortedError) as aborted:
        unsized(0x6060, 0, struct.pack("<L", 9))
    assert aborted.value.code == 0x06090030  # no mode 9
    assert node.sdo[0x6060].raw == 8


def test_an_event_driven_tpdo_also_goes_out_every_event_timer_period(bus: SimulatedBus) -> None:
    node = master(bus)
    tpdo = node.tpdo[2]
    tpdo.clear()
    tpdo.add_variable(0x6041)
    tpdo.trans_type, tpdo.event_timer, tpdo.enabled = 255, 50, True
    node.tpdo.save()
    assert node.sdo[0x1801][5].raw == 50
    cob = tpdo.cob_id
    bus.advance(1.0)
    node.nmt.state = "OPERATIONAL"
    assert bus.times(cob, 0.0) == [1.0]  # on entering OPERATIONAL
    bus.advance(1.3)
    # nothing changed: one every 50 ms
    assert bus.times(cob, 0.0) == pytest.approx([1.0 + 0.05 * k for k in range(7)])
    assert decode_statusword(tpdo[0x6041].raw) is State.SWITCH_ON_DISABLED
    # a change goes out at once and restarts the timer
    bus.advance(1.32)
    node.sdo[0x6040].raw = 0x06
    assert bus.times(cob, 1.3) == [1.32]
    assert decode_statusword(tpdo[0x6041].raw) is State.READY_TO_SWITCH_ON
    bus.advance(1.4)
    assert bus.times(cob, 1.32) == pytest.approx([1.37])
    # a TPDO on SYNC ignores the event timer (CiA 301: types 254 and 255 only)
    node.nmt.state = "PRE-OPERATIONAL"
    tpdo.trans_type = 1
    node.tpdo.save()
    node.nmt.state = "OPERATIONAL"
    mark = bus.now
    bus.advance(mark + 0.3)
    assert bus.times(cob, mark) == []


def test_a_synchronous_acyclic_tpdo_goes_out_on_the_sync_after_its_data_changed(
    bus: SimulatedBus,
) -> None:
    node = master(bus)
    tpdo = node.tpdo[3]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.trans_type, tpdo.enabled = 0, True
    node.tpdo.save()
    cob = tpdo.cob_id
    node.nmt.state = "OPERATIONAL"
    bus.advance(0.1)
    assert bus.times(cob, -1.0) == []  # never without a SYNC
    node.network.sync.transmit()
    assert bus.times(cob, -1.0) == [0.1]  # the first SYNC in OPERATIONAL
    position = tpdo[0x6064].raw
    assert position == node.sdo[0x6064].raw
    bus.advance(0.2)
    node.network.sync.transmit()
    assert bus.times(cob, 0.1) == []  # unchanged
    bus.drive.measure(LENGTH + 0.01, 0.0)
    bus.advance(0.3)
    assert bus.times(cob, 0.1) == []  # changed: waits for the SYNC
    node.network.sync.transmit()
    assert bus.times(cob, 0.1) == [0.3]
    assert tpdo[0x6064].raw == node.sdo[0x6064].raw != position
    bus.advance(0.4)
    node.network.sync.transmit()
    assert bus.times(cob, 0.3) == []


def test_a_synchronous_rpdo_takes_effect_at_the_next_sync(bus: SimulatedBus) -> None:
    """CiA 301: an RPDO of transmission type 0..240 is buffered and acted on at the next
    SYNC; type 254/255 (what cdprd's host configures) acts on reception."""
    node = master(bus)
    for number, kind in ((1, 1), (2, 255)):
        rpdo = node.rpdo[number]
        rpdo.clear()
        rpdo.add_variable(0x6040)
        rpdo.trans_type, rpdo.enabled = kind, True
    node.rpdo.save()
    node.nmt.state = "OPERATIONAL"
    synchronous, event_driven = node.rpdo[1], node.rpdo[2]
    synchronous[0x6040].raw = 0x06
    synchronous.transmit()
    bus.advance(0.05)
    assert state(node) is State.SWITCH_ON_DISABLED and node.sdo[0x6040].raw == 0
    node.network.sync.transmit()
    assert state(node) is State.READY_TO_SWITCH_ON and node.sdo[0x6040].raw == 0x06
    # the latest reception before the SYNC is the one that takes effect
    for word in (0x00, 0x07):
        synchronous[0x6040].raw = word
        synchronous.transmit()
    assert state(node) is State.READY_TO_SWITCH_ON
    node.network.sync.transmit()
    assert state(node) is State.SWITCHED_ON
    node.network.sync.transmit()  # nothing new: nothing happens again
    assert state(node) is State.SWITCHED_ON
    # received, then the drive leaves OPERATIONAL: the buffered data is dropped
    synchronous[0x6040].raw = 0x0F
    synchronous.transmit()
    node.nmt.state = "PRE-OPERATIONAL"
    node.nmt.state = "OPERATIONAL"
    node.network.sync.transmit()
    assert state(node) is State.SWITCHED_ON
    # an event-driven RPDO acts on reception
    event_driven[0x6040].raw = 0x0F
    event_driven.transmit()
    assert state(node) is State.OPERATION_ENABLED
